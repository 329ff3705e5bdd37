"""Predictors for design studies: the forming of a batch of process settings.

Each returns a :data:`~torch_ampn.design.search.Predictor`: a function of setting trajectories
(:func:`~torch_ampn.design.search.settings_trajectories`) to their predicted positions
``[S, N, 3]``, the formed part last: whole rollouts (``S = T + 1``), or the formed part alone
(``S = 1``) from a surrogate predictor with ``final=True``, which is all a search needs.

* :func:`surrogate_predictor`: a trained :class:`~torch_ampn.forming.AMPNSurrogate`, batched on the
  fast path where it applies, with its prior (a fitted baseline) where it has one.
* :func:`baseline_predictor`: a fitted setting-aware baseline (e.g. POD + GP).
* :func:`simulator_predictor`: the embedded simulator, the reference a choice is checked against.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.design.search import Predictor
from torch_ampn.sim.config import StampFormingConfig


def baseline_predictor(baseline: Any) -> Predictor:
    """A fitted baseline's ``predict(traj)`` ``[T + 1, N, 3]`` (all at once where it has ``predict_many``)."""

    def predict(trajs: Sequence[Trajectory]) -> list[Tensor]:
        if hasattr(baseline, "predict_many"):
            return baseline.predict_many(trajs)
        return [baseline.predict(traj) for traj in trajs]

    return predict


def simulator_predictor(
    cfg: StampFormingConfig,
    compile: bool = False,
    batch_size: int = 16,
    progress: bool = False,
    perturbation: float = 0.0,
    seed_offset: int = 0,
) -> Predictor:
    """The embedded simulator for each trajectory's recorded settings (``batch_size`` at a time).

    Reads the gripper settings from ``meta["gripper_edge_fraction"]`` and ``gripper_force``.
    ``perturbation``: start each from ply positions moved by up to this many mm, seeded by
    ``seed_offset`` + the setting's place in the call (another offset: another perturbation; see
    :func:`~torch_ampn.sim.simulate_batch`).
    """
    from torch_ampn.sim import simulate_batch

    def predict(trajs: Sequence[Trajectory]) -> list[Tensor]:
        settings = [(t.meta["gripper_edge_fraction"], t.gripper_force.tolist()) for t in trajs]
        out: list[Tensor] = []
        starts = range(0, len(settings), batch_size)
        if progress:
            from tqdm.auto import tqdm

            starts = tqdm(starts, desc="simulate", unit="batch")
        for i in starts:
            part = settings[i : i + batch_size]
            seeds = range(seed_offset + i, seed_offset + i + len(part))
            trajs = simulate_batch(cfg, seeds, settings=part, compile=compile, perturbation=perturbation)
            out += [t.pos for t in trajs]
        return out

    return predict


def surrogate_predictor(
    surrogate: Any,
    hierarchy: Any,
    prior: Any = None,
    batch_size: int = 8,
    compile: bool = True,
    device: torch.device | str | None = None,
    seed: int = 0,
    final: bool = False,
) -> Predictor:
    """A trained surrogate rolled out over each setting (its noise seeded ``seed`` for every setting).

    Args:
        surrogate: The :class:`~torch_ampn.forming.AMPNSurrogate` or
            :class:`~torch_ampn.forming.direct.DirectSurrogate`.
        hierarchy: Its mesh's hierarchy.
        prior: The fitted baseline a surrogate with ``prior_features`` reads
            (``AMPNDataModule.prior_baseline()``); required for such a surrogate.
        batch_size: Settings per fast-path batch (per network pass of a direct surrogate).
        compile: Compile the fast path.
        device: Where to run.
        seed: Seed of each rollout's noise generator.
        final: Return the formed part alone, ``[1, N, 3]`` per setting. A
            :class:`~torch_ampn.forming.direct.DirectSurrogate` then predicts that one step
            (its decoder runs once instead of ``T`` times); a next-step surrogate still rolls
            out every step and keeps the last.
    """
    from torch_ampn.forming.direct import DirectSurrogate
    from torch_ampn.rollout import rollout_surrogate
    from torch_ampn.rollout.direct import predict_direct

    needs_prior = bool(getattr(surrogate, "prior_features", False))
    if needs_prior and prior is None:
        raise ValueError("this surrogate reads a prior (prior_features): give the fitted prior baseline")

    def predict(trajs: Sequence[Trajectory]) -> list[Tensor]:
        trajs = list(trajs)
        if needs_prior:
            priors = baseline_predictor(prior)(trajs)  # on shallow copies: the caller's stay as they are
            trajs = [dataclasses.replace(t, prior=p) for t, p in zip(trajs, priors, strict=True)]
        if final and isinstance(surrogate, DirectSurrogate):
            finals = predict_direct(surrogate, trajs, hierarchy, batch_size, device=device, final=True)
            return [pos[None] for pos in finals]  # [1, N, 3] each
        dev = device or "cpu"
        gens = [torch.Generator(device=dev).manual_seed(seed) for _ in trajs]
        with warnings.catch_warnings():  # a surrogate without a fast path: the plain one, quietly
            warnings.filterwarnings("ignore", message="no fast rollout")
            rollouts = rollout_surrogate(
                surrogate, trajs, hierarchy, gens, batch_size=min(batch_size, len(trajs)), compile=compile,
                device=device,
            )  # fmt: skip
        return [pos[-1:] for pos in rollouts] if final else rollouts

    return predict


__all__ = ["baseline_predictor", "simulator_predictor", "surrogate_predictor"]
