"""Whole trajectories from a :class:`~torch_ampn.forming.direct.DirectSurrogate`, one pass per batch."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from torch_geometric.data import Batch

from torch_ampn.data.dataset import direct_sample
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.forming.direct import DirectSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData


class _Inputs:
    """Initial-state samples with the surrogate's contact edges, searched once per initial state.

    A direct surrogate's contact edges are those of the initial positions; the settings of a
    design study share one initial state, so its edges are found for the first and copied to
    the rest (only after an exact comparison of the initial positions).
    """

    def __init__(self, surrogate: DirectSurrogate, hierarchy: HierarchicalData) -> None:
        self.surrogate = surrogate
        self.hierarchy = hierarchy
        # (initial positions, a sample); a transform that writes node tables too is not shortcut
        self.known: tuple[Tensor, HierarchicalData] | None = None
        self.shortcut = not surrogate.contact.static

    def __call__(self, traj: Trajectory) -> HierarchicalData:
        """The initial-state sample of ``traj`` (with its prior's displacement, if any; no future is read)."""
        data = direct_sample(traj, self.hierarchy, targets=False)
        if self.known is not None and torch.equal(self.known[0], traj.pos[0]):
            for level in range(data.num_levels):  # what the transform wrote: edge_index (edge_attr)
                store = data.contact(level)
                for key, value in self.known[1].contact(level).items():
                    store[key] = value
            return data
        data = self.surrogate.contact(data)
        if self.shortcut:
            self.known = (traj.pos[0], data)
        return data


@torch.no_grad()
def predict_direct(
    surrogate: DirectSurrogate,
    trajectories: Sequence[Trajectory],
    hierarchy: HierarchicalData,
    batch_size: int = 4,
    device: torch.device | str | None = None,
    num_steps: int | None = None,
    progress: bool = False,
    final: bool = False,
) -> list[Tensor]:
    """The positions of every saved step of trajectories of one mesh, ``batch_size`` per network pass.

    Ply nodes move by the predicted displacement; tool nodes follow each trajectory's prescribed
    motion (``traj.pos``), as in a rollout. The trajectories' ply positions after step 0 are never read.

    Args:
        surrogate: The trained direct surrogate.
        trajectories: Their initial states, gripper settings and tool motion are used.
        hierarchy: The mesh's hierarchy.
        batch_size: Trajectories per network pass (4 is the fastest per trajectory on a 2-core
            CPU with the coarse mesh: 28 ms against 31 with 1 or 8 and 35 with 16;
            ``benchmarks/direct_speed.py``, 2026-12-06).
        device: Where to run (default: the surrogate's device).
        num_steps: Steps to predict (default: all).
        progress: A progress bar over the batches.
        final: Predict the last step only (what a design study of the formed part needs: the
            decoder runs for one time instead of ``T``).

    Returns:
        One ``[num_steps + 1, N, 3]`` position tensor per trajectory (float32, CPU), in order;
        with ``final``, one ``[N, 3]`` tensor of the positions at step ``num_steps``.
    """
    trajs = list(trajectories)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    device = torch.device(device) if device is not None else next(surrogate.parameters()).device
    starts = range(0, len(trajs), batch_size)
    if progress and len(starts) > 1:
        from tqdm.auto import tqdm

        starts = tqdm(starts, desc="settings", unit="batch")
    out: list[Tensor] = []
    inputs = _Inputs(surrogate, hierarchy)
    for i in starts:
        part = trajs[i : i + batch_size]
        total = part[0].num_steps
        if any(t.num_steps != total for t in part):
            raise ValueError("predict_direct: the trajectories of a batch must have one step count")
        steps = total if num_steps is None else num_steps
        if not 1 <= steps <= total:
            raise ValueError(f"num_steps must be in 1..{total}, got {steps}")
        batch = Batch.from_data_list([inputs(t) for t in part]).to(device)
        asked = torch.tensor([steps]) if final else torch.arange(1, steps + 1)
        disp = surrogate.predict_displacement(batch, total, asked)  # [B N, S, 3]
        disp = disp.float().cpu().split([t.num_nodes for t in part])
        for traj, d in zip(part, disp, strict=True):
            if final:
                pos = traj.pos[steps].float().clone()  # tools: their prescribed position
                pos[traj.ply_mask] = traj.pos[0, traj.ply_mask].float() + d[traj.ply_mask, 0]
                out.append(pos)
                continue
            pos = traj.pos[: steps + 1].float().clone()  # tools: their prescribed motion
            ply = traj.ply_mask
            pos[1:, ply] = pos[0, ply] + d.transpose(0, 1)[:, ply]
            out.append(pos)
    return out
