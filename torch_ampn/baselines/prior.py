"""Priors: a setting-aware baseline's trajectory as an input of a learned surrogate.

A model with ``prior_features`` (:class:`~torch_ampn.forming.AMPNSurrogate`) reads, at every step,
where a prior prediction of the whole trajectory puts each node
(:func:`~torch_ampn.forming.features.prior_features`) and learns to correct it. The prior is one of
:mod:`torch_ampn.baselines.settings`, by default POD + GP.

A prior must be as good on the training trajectories as it will be on unseen settings, or the
network learns to trust it more than it deserves: the GP reproduces its training trajectories
almost exactly. So the training split's priors are *out of fold* (:func:`out_of_fold_priors`:
each trajectory's prior comes from a fit on the other folds), and every other split's from a
fit on the whole training split (:func:`fitted_prior`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from torch import Tensor

from torch_ampn.baselines.settings import TrajectoryBaseline, setting_baselines
from torch_ampn.data.trajectory import Trajectory

#: Names of the baselines a prior can be (those of :func:`~torch_ampn.baselines.setting_baselines`).
PRIOR_NAMES = ("mean_trajectory", "nearest_setting", "linear_settings", "pod_gp")


def make_prior(name: str) -> TrajectoryBaseline:
    """An unfitted baseline of :data:`PRIOR_NAMES` by name (``ValueError`` naming the choices)."""
    if name not in PRIOR_NAMES:
        raise ValueError(f"prior must be one of {PRIOR_NAMES}, got {name!r}")
    return setting_baselines()[name]


def fitted_prior(name: str, trajectories: Sequence[Trajectory]) -> TrajectoryBaseline:
    """The baseline ``name`` fitted on ``trajectories`` (one mesh)."""
    return make_prior(name).fit(trajectories)


def out_of_fold_priors(
    name: str,
    trajectories: Sequence[Trajectory],
    folds: int = 5,
    seed: int = 0,
    progress: bool = False,
) -> list[Tensor]:
    """Each trajectory's prior ``[T+1, N, 3]`` from the baseline ``name`` fitted on the other folds.

    The trajectories are split into ``folds`` groups at random (``seed``); the baseline is fitted
    ``folds`` times, on all groups but one, and predicts the left-out group. Tool nodes follow
    each trajectory's own prescribed motion.

    Raises:
        ValueError: If ``folds`` is below 2 or above the number of trajectories.
    """
    trajectories = list(trajectories)
    if not 2 <= folds <= len(trajectories):
        raise ValueError(f"folds must be in 2..{len(trajectories)} (the trajectories), got {folds}")
    order = np.random.default_rng(seed).permutation(len(trajectories))
    groups = np.array_split(order, folds)
    priors: list[Tensor | None] = [None] * len(trajectories)
    steps: Callable = _progress(folds, progress)
    for held_out in groups:
        rest = set(held_out.tolist())
        baseline = fitted_prior(name, [t for i, t in enumerate(trajectories) if i not in rest])
        for i in held_out.tolist():
            priors[i] = baseline.predict(trajectories[i])
        steps()
    return priors  # type: ignore[return-value]


def _progress(total: int, enabled: bool) -> Callable[[], None]:
    """A callable that advances a progress bar of ``total`` folds (a no-op when disabled)."""
    if not enabled:
        return lambda: None
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc="out-of-fold priors", unit="fold", leave=False)

    def step() -> None:
        bar.update()
        if bar.n >= total:
            bar.close()

    return step
