"""Graph data: the AMG hierarchy, ``HierarchicalData`` and mesh builders."""

from torch_ampn.data.dataset import (
    HierarchyCache,
    StepDataset,
    TrajectoryDataset,
    check_dataset,
    set_window,
    step_sample,
)
from torch_ampn.data.hierarchical_data import HierarchicalData, level_name
from torch_ampn.data.hierarchy import build_hierarchy, mesh_operator
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

__all__ = [
    "HierarchicalData",
    "HierarchyCache",
    "MultiComponentMesh",
    "NodeType",
    "StepDataset",
    "Trajectory",
    "TrajectoryDataset",
    "TrajectoryFormatError",
    "build_hierarchy",
    "cells_to_edge_index",
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
    "step_sample",
]
