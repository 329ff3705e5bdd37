"""The AMG graph hierarchy of any mesh: :class:`HierarchicalData` and :func:`build_hierarchy`.

Part of the generic core (with :mod:`torch_ampn.nn` and :mod:`torch_ampn.transforms`): nothing
here knows about stamp forming. On a PyG ``Data``, :class:`torch_ampn.transforms.AMGHierarchy`
builds the hierarchy with positions and edge features.
"""

from torch_ampn.hierarchy.amg import build_hierarchy, mesh_operator
from torch_ampn.hierarchy.hierarchical_data import (
    CONTACT,
    DOWN,
    MESH,
    RELATIONS,
    UP,
    EdgeType,
    HierarchicalData,
    check_level_counts,
    edge_type,
    level_name,
)

__all__ = [
    "CONTACT",
    "DOWN",
    "MESH",
    "RELATIONS",
    "UP",
    "EdgeType",
    "HierarchicalData",
    "build_hierarchy",
    "check_level_counts",
    "edge_type",
    "level_name",
    "mesh_operator",
]
