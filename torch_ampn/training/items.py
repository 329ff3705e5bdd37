"""Whole-trajectory items for validation, test and predict dataloaders."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch_ampn.data.hierarchical_data import HierarchicalData
from torch_ampn.data.trajectory import Trajectory


@dataclass
class RolloutItem:
    """One trajectory to roll out, with its hierarchy.

    Attributes:
        index: Position in its split (seeds the rollout's noise input).
        name: Label used in tables and file names (the file stem, e.g. ``traj_200000``).
        trajectory: The trajectory (ground truth, or a process setting from
            :func:`~torch_ampn.sim.process_trajectory` for ``predict``).
        hierarchy: The hierarchy of its mesh.
    """

    index: int
    name: str
    trajectory: Trajectory
    hierarchy: HierarchicalData


class RolloutDataset:
    """Map-style dataset of :class:`RolloutItem` (use with ``DataLoader(batch_size=None)``).

    Args:
        names: One label per trajectory.
        load: ``i -> Trajectory`` (called lazily, results are not cached here).
        hierarchy: ``Trajectory -> HierarchicalData`` (e.g. a :class:`~torch_ampn.data.HierarchyCache`).
    """

    def __init__(
        self,
        names: Sequence[str],
        load: Callable[[int], Trajectory],
        hierarchy: Callable[[Trajectory], HierarchicalData],
    ) -> None:
        self.names = list(names)
        self.load = load
        self.hierarchy = hierarchy

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> RolloutItem:
        traj = self.load(i)
        return RolloutItem(i, self.names[i], traj, self.hierarchy(traj))


def identity_collate(item: RolloutItem) -> RolloutItem:
    """``collate_fn`` that passes an item through unchanged (picklable for worker processes)."""
    return item
