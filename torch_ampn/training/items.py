"""Whole-trajectory items for validation, test and predict dataloaders."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch.distributed as dist
from torch.utils.data import DistributedSampler

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


def list_collate(items: list[RolloutItem]) -> list[RolloutItem]:
    """``collate_fn`` of batches of items: the list itself (picklable for worker processes)."""
    return list(items)


class EachOnceSampler(DistributedSampler):
    """Items ``rank, rank + world_size, ...`` of a dataset: every item exactly once over all ranks.

    PyTorch's ``DistributedSampler`` repeats items to give every rank as many; a rollout
    metric must not count a trajectory twice. Without ``torch.distributed`` (one process)
    it yields every item in order. Being a ``DistributedSampler``, Lightning keeps it.
    """

    def __init__(self, dataset: Sequence) -> None:
        distributed = dist.is_available() and dist.is_initialized()
        num_replicas = dist.get_world_size() if distributed else 1
        rank = dist.get_rank() if distributed else 0
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.rank, len(self.dataset), self.num_replicas))

    def __len__(self) -> int:
        return len(range(self.rank, len(self.dataset), self.num_replicas))


def gather_objects(value: object) -> list[object]:
    """``value`` of every rank (a list of one without ``torch.distributed``)."""
    if not (dist.is_available() and dist.is_initialized()):
        return [value]
    out: list[object] = [None] * dist.get_world_size()
    dist.all_gather_object(out, value)
    return out
