"""Rolling out an :class:`~torch_ampn.forming.AMPNSurrogate`: the one place that chooses the path.

The fast path (:class:`~torch_ampn.rollout.FastRollout`: static shapes, compiled, batched over
settings) where the surrogate's settings have one, else the plain path
(:func:`~torch_ampn.rollout.rollout`), with a warning that says why. Both give the same
positions up to floating-point summation order, with the same noise draws per generator.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence

import torch
from torch import Tensor

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.rollout.fast import cached_fast_rollout, fast_path_supported
from torch_ampn.rollout.plain import rollout


def rollout_surrogate(
    surrogate: AMPNSurrogate,
    trajectories: Sequence[Trajectory],
    hierarchy: HierarchicalData,
    generators: Sequence[torch.Generator | None],
    *,
    fast: bool = True,
    batch_size: int = 1,
    compile: bool = True,
    device: torch.device | str | None = None,
    num_steps: int | None = None,
    progress: bool = False,
) -> list[Tensor]:
    """Roll ``surrogate`` out over trajectories of one mesh, each with its noise generator.

    Args:
        surrogate: The trained surrogate.
        trajectories: Their initial states, gripper settings and tool motion are used.
        hierarchy: The mesh's hierarchy.
        generators: One noise generator per trajectory (``None``: the default generator).
        fast: Take the fast path where the surrogate's settings allow it (else, and with
            ``False``, the plain path; asked for and unavailable, it warns).
        batch_size: Trajectories per fast-path call (its compiled batch size).
        compile: Compile the fast path.
        device: Where to run (default: the surrogate's device on the fast path, the
            hierarchy's on the plain one).
        num_steps: Steps to roll out (default: all).
        progress: A progress bar: over the steps for one batch, over the batches for more.

    Returns:
        One ``[num_steps + 1, N, 3]`` position tensor per trajectory (float32, CPU), in order.
    """
    trajs, gens = list(trajectories), list(generators)
    if len(gens) != len(trajs):
        raise ValueError(f"got {len(gens)} generators for {len(trajs)} trajectories")
    reason = fast_path_supported(surrogate) if fast else None
    if fast and reason is None:
        runner = cached_fast_rollout(
            surrogate, hierarchy, batch_size=batch_size, compile=compile, device=device
        )
        b = runner.batch_size
        starts = range(0, len(trajs), b)
        many = len(starts) > 1
        if progress and many:
            from tqdm.auto import tqdm

            starts = tqdm(starts, desc="settings", unit="batch")
        out: list[Tensor] = []
        for i in starts:
            out.extend(
                runner(trajs[i : i + b], gens[i : i + b], num_steps=num_steps, progress=progress and not many)
            )
        return out
    if fast:
        warnings.warn(f"no fast rollout ({reason}); taking the plain path", RuntimeWarning, stacklevel=3)
    return [
        rollout(
            functools.partial(surrogate.predict_residual, generator=g),
            traj,
            hierarchy,
            surrogate.contact,
            num_steps=num_steps,
            device=device,
            progress=progress,
        )
        for traj, g in zip(trajs, gens, strict=True)
    ]
