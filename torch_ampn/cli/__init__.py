"""The command-line programs.

* :mod:`~torch_ampn.cli.train`: ``torch-ampn`` (Lightning's ``fit``/``validate``/``test``/``predict``,
  and ``design``),
* :mod:`~torch_ampn.cli.design`: ``torch-ampn design`` (a design study on a trained surrogate),
* :mod:`~torch_ampn.cli.data`: ``torch-ampn-data`` (generate, check, spread, convert, export).
"""
