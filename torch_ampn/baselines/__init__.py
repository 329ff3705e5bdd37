"""Baselines a learned surrogate must beat.

* Trivial ones, which ignore the training data (:mod:`~torch_ampn.baselines.trivial`):
  :func:`static_plies`, :class:`RigidWithPunch` (residual predictors for
  :func:`~torch_ampn.rollout.rollout`).
* Setting-aware ones, built from the training trajectories of one mesh
  (:mod:`~torch_ampn.baselines.settings`): :class:`MeanTrajectory`, :class:`NearestSetting`,
  :class:`PODRegression` (POD plus a Gaussian process, RBF or linear regression on the
  process settings), and :func:`setting_effect_r2`.
* Across a family of parts (:mod:`~torch_ampn.baselines.family`): :class:`PerPlyCount`, one
  baseline per ply count on the settings and :func:`part_parameters`, and
  :func:`family_baselines`.
* Priors (:mod:`~torch_ampn.baselines.prior`): a setting-aware baseline's trajectory as an
  input of a surrogate with ``prior_features``: :func:`fitted_prior`, :func:`out_of_fold_priors`.
"""

from torch_ampn.baselines.family import PerPlyCount, family_baselines, part_parameters
from torch_ampn.baselines.prior import PRIOR_NAMES, fitted_prior, make_prior, out_of_fold_priors
from torch_ampn.baselines.settings import (
    MeanTrajectory,
    NearestSetting,
    PODRegression,
    TrajectoryBaseline,
    fit_setting_baselines,
    process_settings,
    rollout_mse,
    setting_baselines,
    setting_effect_r2,
    setting_names,
)
from torch_ampn.baselines.trivial import RigidWithPunch, static_plies

__all__ = [
    "PRIOR_NAMES",
    "MeanTrajectory",
    "NearestSetting",
    "PODRegression",
    "PerPlyCount",
    "RigidWithPunch",
    "TrajectoryBaseline",
    "family_baselines",
    "fit_setting_baselines",
    "fitted_prior",
    "make_prior",
    "out_of_fold_priors",
    "part_parameters",
    "process_settings",
    "rollout_mse",
    "setting_baselines",
    "setting_effect_r2",
    "setting_names",
    "static_plies",
]
