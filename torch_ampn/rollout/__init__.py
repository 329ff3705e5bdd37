"""Autoregressive rollouts of a next-step predictor over a whole trajectory.

:mod:`~torch_ampn.rollout.plain` rolls out any predictor window by window
(:func:`rollout_plain`) and holds the error metric (:func:`rollout_rmse`);
:mod:`~torch_ampn.rollout.fast` rolls an :class:`~torch_ampn.forming.AMPNSurrogate` out with static
shapes, compiled and batched over process settings (:class:`FastRollout`);
:mod:`~torch_ampn.rollout.surrogate` is the one place that chooses between them
(:func:`rollout`, :func:`rollout_surrogate`, :func:`rollout_settings`).
"""

from torch_ampn.rollout.cache import cached_fast_rollout
from torch_ampn.rollout.fast import FastPathUnavailable, FastRollout, fast_path_supported
from torch_ampn.rollout.plain import Predictor, Transform, one_step_predictions, rollout_plain, rollout_rmse
from torch_ampn.rollout.surrogate import rollout, rollout_settings, rollout_surrogate

__all__ = [
    "FastPathUnavailable",
    "FastRollout",
    "Predictor",
    "Transform",
    "cached_fast_rollout",
    "fast_path_supported",
    "one_step_predictions",
    "rollout",
    "rollout_plain",
    "rollout_rmse",
    "rollout_settings",
    "rollout_surrogate",
]
