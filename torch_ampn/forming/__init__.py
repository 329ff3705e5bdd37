"""The stamp-forming surrogates: their input features, normalisers, the next-step and the direct predictor.

Built on the generic layers of :mod:`torch_ampn.nn`: :class:`AMPNSurrogate` turns a window of
a forming trajectory (:class:`~torch_ampn.data.HierarchicalData`) into the paper's features
(:mod:`torch_ampn.forming.features`), normalises them (:class:`Normalizer`) and predicts the
next ply displacements with a :class:`~torch_ampn.nn.RobinAMPN`; :class:`DirectSurrogate` predicts
every step of a trajectory at once from the initial state and the settings. :func:`ampn_channels`
gives the sizes they need for these features; :func:`load_surrogate` reads a model file of either.
"""

from torch_ampn.forming.direct import DirectSurrogate
from torch_ampn.forming.features import (
    ampn_channels,
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
    prior_features,
    step_features,
)
from torch_ampn.forming.model_file import load_surrogate
from torch_ampn.forming.normalizer import Normalizer
from torch_ampn.forming.surrogate import AMPNSurrogate

__all__ = [
    "AMPNSurrogate",
    "DirectSurrogate",
    "Normalizer",
    "ampn_channels",
    "coarse_node_features",
    "component_features",
    "edge_features",
    "fine_node_features",
    "gripper_features",
    "hierarchical_features",
    "load_surrogate",
    "node_type_one_hot",
    "num_coarse_node_features",
    "num_edge_features",
    "num_fine_node_features",
    "prior_features",
    "step_features",
]
