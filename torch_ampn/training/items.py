"""Samplers and items of the dataloaders: resumable shuffled training windows, whole trajectories."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch.distributed as dist
from torch.utils.data import DistributedSampler
from torch_geometric.loader import DataLoader

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData


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
        num_replicas, rank = _world()
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


def _world() -> tuple[int, int]:
    """``(world size, rank)`` of ``torch.distributed``, ``(1, 0)`` without it."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(), dist.get_rank()
    return 1, 0


class ResumableShuffleSampler(DistributedSampler):
    """Shuffled training items that a resumed fit continues exactly where the stopped one was.

    PyTorch's ``DistributedSampler`` with ``shuffle=True`` (a permutation seeded ``seed +
    epoch``, split over the ranks; one process without ``torch.distributed``), so the order
    depends on the seed and the epoch only, not on how much randomness was drawn before; and
    being a ``DistributedSampler``, Lightning keeps it under DDP. :meth:`resume` makes the next
    epoch it yields skip the items of the batches a stopped run had already trained on.

    Args:
        dataset: The training windows.
        batch_size: Items per batch (to turn batches into items).
        seed: Seed of the permutations (the same on every rank).
    """

    def __init__(self, dataset: Sequence, batch_size: int, seed: int = 0) -> None:
        num_replicas, rank = _world()
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed)
        self.batch_size = batch_size
        self._resume_batches = 0

    @property
    def batches_per_epoch(self) -> int:
        """Batches of this rank per epoch (the last one may be short)."""
        return math.ceil(self.num_samples / self.batch_size)

    def resume(self, batches_done: int) -> None:
        """Skip what ``batches_done`` batches (over all epochs, this rank's) consumed, once."""
        if batches_done < 0:
            raise ValueError(f"batches_done must be >= 0, got {batches_done}")
        self._resume_batches = batches_done

    def __iter__(self) -> Iterator[int]:
        indices = list(super().__iter__())  # [num_samples] of this rank, epoch self.epoch
        skip = max(self._resume_batches - self.epoch * self.batches_per_epoch, 0) * self.batch_size
        self._resume_batches = 0
        return iter(indices[skip:])


class ResumableLoader(DataLoader):
    """PyG ``DataLoader`` over a :class:`ResumableShuffleSampler` whose position Lightning checkpoints.

    Lightning saves the ``state_dict`` of every training loader that has one in its
    checkpoints and hands it back to ``load_state_dict`` when a fit resumes, before the
    loader is iterated. The position is the number of batches trained on so far, read from
    ``batches_done`` (the trainer's optimizer steps times the accumulated batches): the loader
    itself runs a batch ahead of training (Lightning prefetches one).

    Args:
        dataset: The training windows.
        sampler: Their sampler.
        batches_done: Batches trained on so far (called when a checkpoint is saved).
        **kwargs: Further arguments of ``torch_geometric.loader.DataLoader``.
    """

    def __init__(
        self,
        dataset: Sequence,
        sampler: ResumableShuffleSampler,
        batches_done: Callable[[], int],
        **kwargs: Any,
    ) -> None:
        super().__init__(dataset, batch_size=sampler.batch_size, sampler=sampler, **kwargs)
        self.batches_done = batches_done

    def state_dict(self) -> dict[str, int]:
        """``{"batches_done": ...}`` for the checkpoint."""
        return {"batches_done": int(self.batches_done())}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Continue after ``state["batches_done"]`` batches (see :meth:`ResumableShuffleSampler.resume`)."""
        self.sampler.resume(int(state.get("batches_done", 0)))
