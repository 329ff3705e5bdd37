"""Neural network layers and models: IntraLevelConv, InterLevelConv, AMPN and its ROBIN (diffusion) mode."""

from torch_ampn.nn.ampn import AMPN
from torch_ampn.nn.diffusion import DiffusionAMPN, geometric_beta_schedule, pointwise_loss
from torch_ampn.nn.encoding import FourierLevelEncoding
from torch_ampn.nn.features import (
    coarse_node_features,
    component_features,
    edge_features,
    fine_node_features,
    gripper_features,
    hierarchical_features,
    node_type_one_hot,
    num_coarse_node_features,
    num_edge_features,
    num_fine_node_features,
)
from torch_ampn.nn.inter_level_conv import InterLevelConv
from torch_ampn.nn.intra_level_conv import IntraLevelConv
from torch_ampn.nn.mlp import LayerNormMLP
from torch_ampn.nn.multilevel_loss import multilevel_mse, restrict_mean
from torch_ampn.nn.normalizer import Normalizer
from torch_ampn.nn.slots import SlottedEdgeIndex, incoming_slots
from torch_ampn.nn.surrogate import AMPNSurrogate

__all__ = [
    "AMPN",
    "AMPNSurrogate",
    "DiffusionAMPN",
    "FourierLevelEncoding",
    "InterLevelConv",
    "IntraLevelConv",
    "LayerNormMLP",
    "Normalizer",
    "SlottedEdgeIndex",
    "coarse_node_features",
    "component_features",
    "edge_features",
    "fine_node_features",
    "geometric_beta_schedule",
    "gripper_features",
    "hierarchical_features",
    "incoming_slots",
    "multilevel_mse",
    "node_type_one_hot",
    "num_coarse_node_features",
    "num_edge_features",
    "num_fine_node_features",
    "pointwise_loss",
    "restrict_mean",
]
