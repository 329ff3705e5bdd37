"""Process-level helpers of the package: how torch's threads wait, ``torch.compile`` and the heap.

Nothing here imports torch at package import: :mod:`~torch_ampn.utils.threads` must run before
torch starts its thread pool (``import torch_ampn`` calls it first).
"""
