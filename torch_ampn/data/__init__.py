"""Forming data: trajectories, datasets, meshes of laminates and tools, and their readers and writers.

``HierarchicalData``, ``build_hierarchy``, ``check_level_counts`` and ``mesh_operator`` are the
generic core's (:mod:`torch_ampn.hierarchy`), named here too for the forming code.
"""

from torch_ampn.data.dataset import (
    DirectDataset,
    HierarchyCache,
    StepDataset,
    TrajectoryDataset,
    check_dataset,
    direct_sample,
    set_window,
    step_sample,
)
from torch_ampn.data.mesh import (
    MultiComponentMesh,
    cells_to_edge_index,
    laminate_mesh,
    rectangle_mesh,
    stacked_plates,
)
from torch_ampn.data.meshio_io import export_vtu_series, export_xdmf, read_time_series
from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError, gripper_forces, gripper_points
from torch_ampn.hierarchy import (
    HierarchicalData,
    build_hierarchy,
    check_level_counts,
    level_name,
    mesh_operator,
)

__all__ = [
    "HierarchicalData",
    "HierarchyCache",
    "MultiComponentMesh",
    "NodeType",
    "DirectDataset",
    "StepDataset",
    "Trajectory",
    "TrajectoryDataset",
    "TrajectoryFormatError",
    "build_hierarchy",
    "cells_to_edge_index",
    "check_level_counts",
    "export_vtu_series",
    "export_xdmf",
    "laminate_mesh",
    "level_name",
    "mesh_operator",
    "read_time_series",
    "rectangle_mesh",
    "stacked_plates",
    "check_dataset",
    "gripper_forces",
    "gripper_points",
    "set_window",
    "direct_sample",
    "step_sample",
]
