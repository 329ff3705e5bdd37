"""Graph transforms: contact edges between components."""

from torch_ampn.transforms.contact import (
    ComponentRadiusGraph,
    component_radius_graph,
    component_radius_table,
    plain_radius_graph,
    table_to_edge_index,
    torch_cluster_available,
)

__all__ = [
    "ComponentRadiusGraph",
    "component_radius_graph",
    "component_radius_table",
    "plain_radius_graph",
    "table_to_edge_index",
    "torch_cluster_available",
]
