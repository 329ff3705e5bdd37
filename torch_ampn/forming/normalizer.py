"""Feature normalisation from training statistics (:class:`torch_ampn.nn.Normalizer`, imported here)."""

from torch_ampn.nn.normalizer import Normalizer

__all__ = ["Normalizer"]
