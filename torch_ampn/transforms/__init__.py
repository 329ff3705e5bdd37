"""Graph transforms: the AMG hierarchy of a mesh, contact edges between components."""

from torch_ampn.transforms._cluster import torch_cluster_available
from torch_ampn.transforms._native import native_available
from torch_ampn.transforms.contact import ComponentRadiusGraph
from torch_ampn.transforms.hierarchy import AMGHierarchy
from torch_ampn.transforms.radius import (
    component_radius_graph,
    component_radius_table,
    plain_radius_graph,
    table_to_edge_index,
)

__all__ = [
    "AMGHierarchy",
    "ComponentRadiusGraph",
    "component_radius_graph",
    "component_radius_table",
    "native_available",
    "plain_radius_graph",
    "table_to_edge_index",
    "torch_cluster_available",
]
