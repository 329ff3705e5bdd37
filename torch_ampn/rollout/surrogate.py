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
from torch_ampn.forming.direct import DirectSurrogate
from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.rollout.cache import cached_fast_rollout
from torch_ampn.rollout.direct import predict_direct
from torch_ampn.rollout.fast import FastPathUnavailable, fast_path_supported
from torch_ampn.rollout.plain import Predictor, Transform, rollout_plain


def rollout_surrogate(
    surrogate: AMPNSurrogate | DirectSurrogate,
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

    A :class:`~torch_ampn.forming.direct.DirectSurrogate` is not rolled out: it predicts every
    step in one pass per ``batch_size`` trajectories (:func:`~torch_ampn.rollout.direct.predict_direct`;
    ``generators``, ``fast`` and ``compile`` do not apply).

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
    if isinstance(surrogate, DirectSurrogate):  # no rollout: one pass per batch of settings
        return predict_direct(
            surrogate, trajs, hierarchy, batch_size=batch_size, device=device, num_steps=num_steps,
            progress=progress,
        )  # fmt: skip
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
        rollout_plain(
            functools.partial(surrogate.predict_residual, generator=g),
            traj,
            hierarchy,
            surrogate.contact,
            num_steps=num_steps,
            device=device,
            progress=progress,
            bundle_steps=surrogate.bundle_steps,
        )
        for traj, g in zip(trajs, gens, strict=True)
    ]


@torch.no_grad()
def rollout(
    predictor: Predictor,
    traj: Trajectory,
    hierarchy: HierarchicalData,
    contact: Transform | None = None,
    num_steps: int | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    *,
    fast: bool = False,
    generator: torch.Generator | None = None,
    compile: bool = True,
    bundle_steps: int | None = None,
) -> Tensor:
    """Roll ``predictor`` out over ``traj`` from its initial state.

    A :class:`~torch_ampn.forming.direct.DirectSurrogate` (the main job's model) is not rolled
    out: it predicts every step in one pass (:func:`~torch_ampn.rollout.direct.predict_direct`;
    ``contact``, ``fast``, ``generator`` and ``compile`` do not apply), with the same result shape.

    Args:
        predictor: ``HierarchicalData -> [N, 3]`` residual of every fine node, in mm, or a direct
            surrogate.
        traj: The trajectory: its initial state, mesh, gripper settings and tool motion are
            used; its ply positions after step 0 are never read.
        hierarchy: The hierarchy of ``traj``'s mesh (e.g. from
            :class:`~torch_ampn.data.HierarchyCache`); not modified.
        contact: Transform that fills the contact edges from current positions (e.g.
            ``surrogate.contact``); ``None`` for no contact edges. A transform whose
            ``positions`` is ``"initial"`` runs once, its edges serve every step.
        num_steps: Steps to roll out (default: all ``T``).
        device: Where to run (default: the hierarchy's device).
        progress: Show a progress bar.
        fast: Use the static-shape path (:class:`~torch_ampn.rollout.fast.FastRollout`):
            ``predictor`` must then be an :class:`~torch_ampn.forming.AMPNSurrogate` (its own contact
            settings are used; ``contact`` is ignored) and the noise comes from ``generator``.
            Same result up to floating-point summation order. Where the surrogate's settings
            have no fast path (plain-radius contact) it warns and takes the plain path.
        generator: Noise generator of the fast path (the plain path's predictor brings its own).
        compile: Compile the fast path (``torch.compile``; it warns and runs eagerly where that fails).
        bundle_steps: Steps per call of the plain path's ``predictor`` (``[N, 3 B]`` offsets; see
            :func:`~torch_ampn.rollout.rollout_plain`); ``None``: a bundled surrogate's (or its
            method's) own ``bundle_steps``, else 1.

    Returns:
        Predicted positions ``[num_steps + 1, N, 3]`` (float32, on the CPU); row 0 is the initial state.
    """
    if isinstance(predictor, DirectSurrogate):
        return predict_direct(predictor, [traj], hierarchy, device=device, num_steps=num_steps)[0]
    if not fast:
        bundle = _bundle_steps(predictor) if bundle_steps is None else bundle_steps
        return rollout_plain(
            predictor, traj, hierarchy, contact, num_steps, device, progress, bundle_steps=bundle
        )
    if not isinstance(predictor, AMPNSurrogate):
        raise TypeError(
            f"rollout(fast=True) needs an AMPNSurrogate as predictor, got {type(predictor).__name__}"
        )
    steps = traj.num_steps if num_steps is None else num_steps
    if not 1 <= steps <= traj.num_steps:
        raise ValueError(f"num_steps must be in 1..{traj.num_steps}, got {steps}")
    return rollout_surrogate(
        predictor, [traj], hierarchy, [generator], compile=compile, device=device, num_steps=steps,
        progress=progress,
    )[0]  # fmt: skip


def rollout_settings(
    surrogate: AMPNSurrogate,
    trajectories: Sequence[Trajectory],
    hierarchy: HierarchicalData,
    batch_size: int = 8,
    generators: Sequence[torch.Generator | None] | None = None,
    compile: bool = True,
    device: torch.device | str | None = None,
    progress: bool = False,
) -> list[Tensor]:
    """Roll out many process settings of one mesh, ``batch_size`` at a time (a design study).

    Args:
        surrogate: The trained surrogate.
        trajectories: The settings, e.g. from :func:`~torch_ampn.sim.process_trajectory` (same mesh).
        hierarchy: The mesh's hierarchy.
        batch_size: Settings per batch (the last batch is padded).
        generators: One noise generator per setting (default: generators seeded 0, 1, 2, ...).
        compile: Compile the step (see :class:`FastRollout`).
        device: Where to run.
        progress: Show a progress bar over the batches.

    Returns:
        One ``[T + 1, N, 3]`` position tensor per setting (CPU), in the given order; equal to
        rolling each setting out alone with its generator.
    """
    trajs = list(trajectories)
    if generators is None:  # on the device the rollout runs on (the noise is drawn there)
        dev = torch.device(device) if device is not None else next(surrogate.parameters()).device
        generators = [torch.Generator(device=dev).manual_seed(i) for i in range(len(trajs))]
    reason = fast_path_supported(surrogate)
    if reason is not None:
        raise FastPathUnavailable(f"no fast rollout: {reason}")
    size = min(batch_size, len(trajs))
    return rollout_surrogate(
        surrogate,
        trajs,
        hierarchy,
        generators,
        batch_size=size,
        compile=compile,
        device=device,
        progress=progress,
    )


def _bundle_steps(predictor: Predictor) -> int:
    """Steps per call of ``predictor``: a (bound method of a) bundled surrogate's ``bundle_steps``, else 1."""
    owner = getattr(getattr(predictor, "func", predictor), "__self__", predictor)  # partial, bound method
    return int(getattr(owner, "bundle_steps", 1))
