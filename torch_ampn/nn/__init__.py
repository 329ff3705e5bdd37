"""Layers any PyG user can reuse: IntraLevelConv, InterLevelConv, AMPN, its ROBIN (diffusion) mode.

Nothing here knows about stamp forming: the forming surrogate (its features, normalisers and
the next-step predictor) is :mod:`torch_ampn.forming`.
"""

from torch_ampn.nn.ampn import AMPN
from torch_ampn.nn.diffusion import DiffusionAMPN, RobinAMPN, geometric_beta_schedule, pointwise_loss
from torch_ampn.nn.encoding import FourierLevelEncoding
from torch_ampn.nn.inter_level_conv import InterLevelConv
from torch_ampn.nn.intra_level_conv import IntraLevelConv
from torch_ampn.nn.mlp import LayerNormMLP
from torch_ampn.nn.multilevel_loss import multilevel_mse
from torch_ampn.nn.normalizer import Normalizer
from torch_ampn.nn.slots import SlottedEdgeIndex, incoming_slots
from torch_ampn.nn.transfer import restrict_mean, weighted_mean

__all__ = [
    "AMPN",
    "DiffusionAMPN",
    "FourierLevelEncoding",
    "InterLevelConv",
    "IntraLevelConv",
    "LayerNormMLP",
    "Normalizer",
    "RobinAMPN",
    "SlottedEdgeIndex",
    "geometric_beta_schedule",
    "incoming_slots",
    "multilevel_mse",
    "pointwise_loss",
    "restrict_mean",
    "weighted_mean",
]
