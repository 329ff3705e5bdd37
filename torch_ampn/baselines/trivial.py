"""Trivial rollout baselines, which ignore the training data.

Predictors for :func:`~torch_ampn.rollout.rollout`.

* :func:`static_plies`: the plies stay where they are.
* :class:`RigidWithPunch`: ply nodes touching the punch (within ``touch_radius`` of a punch
  node) move rigidly with it; the others stay.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.transforms.radius import component_radius_table


def static_plies(data: HierarchicalData) -> Tensor:
    """Zero residual everywhere: ``[N, 3]`` zeros (plies never move)."""
    return torch.zeros_like(data["l0"].pos)


class RigidWithPunch:
    """Ply nodes within ``touch_radius`` of the punch take the motion of their nearest punch node.

    Args:
        touch_radius: Distance (mm) from a ply node to the nearest punch node below which it
            counts as touching (default 3 mm, the contact radius; plies are 0.5 mm apart).
    """

    def __init__(self, touch_radius: float = 3.0) -> None:
        if touch_radius <= 0:
            raise ValueError(f"touch_radius must be > 0, got {touch_radius}")
        self.touch_radius = float(touch_radius)

    def __call__(self, data: HierarchicalData) -> Tensor:
        """Residual ``[N, 3]``: the nearest punch node's motion ``bc_disp`` on touching ply nodes, else 0."""
        fine = data["l0"]
        punch = fine.node_type == NodeType.PUNCH  # [N]
        label = (~punch).long()  # punch: 0, everything else: 1
        nbr, mask = component_radius_table(fine.pos, label, self.touch_radius, 1, num_components=2)  # [N, 1]
        touching = mask[:, 0] & (fine.node_type == NodeType.PLY)  # [N]
        motion = fine.bc_disp[nbr[:, 0]]  # [N, 3]
        return torch.where(touching[:, None], motion, torch.zeros_like(motion))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(touch_radius={self.touch_radius})"
