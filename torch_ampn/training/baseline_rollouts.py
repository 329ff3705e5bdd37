"""The baselines ``torch-ampn test`` reports next to the model, rolled out on each test trajectory."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torch_ampn.baselines import RigidWithPunch, fit_setting_baselines, static_plies
from torch_ampn.baselines.family import UnplaceablePart
from torch_ampn.rollout import rollout, rollout_rmse
from torch_ampn.training.items import RolloutItem
from torch_ampn.training.protocol import forecast_source


class BaselineRollouts:
    """Trivial and setting-aware baselines of a test report.

    Trivial: the plies left where they start (``static``) and moved rigidly with the punch
    within each touch radius (``rigid_r<radius>``); they ignore the training data. Setting-aware
    (:func:`~torch_ampn.baselines.fit_setting_baselines`): fitted on the training trajectories.

    On a family of parts, a setting-aware baseline cannot place a part of a tool shape or ply
    count that no training part had: its curve is NaN there (so the report leaves it out of the
    comparison) and :attr:`refused` says why.

    Args:
        touch_radii: Radii (mm) of the rigid-with-punch baselines.
        setting_baselines: Fitted setting-aware baselines by name (``{}``: none).
    """

    def __init__(self, touch_radii: Sequence[float], setting_baselines: dict[str, Any] | None = None) -> None:
        self.touch_radii = tuple(touch_radii)
        self.setting_baselines = dict(setting_baselines or {})
        #: Why a setting-aware baseline was not applied to some trajectory, by name (the first reason).
        self.refused: dict[str, str] = {}

    @classmethod
    def fitted(cls, datamodule: Any, touch_radii: Sequence[float]) -> tuple[BaselineRollouts, str | None]:
        """The baselines with the setting-aware ones fitted on ``datamodule``'s training split.

        Returns ``(baselines, reason)``: ``reason`` says why no setting-aware baseline is
        reported (no training split, fewer than 2 trajectories, ...), else ``None``.
        """
        source = forecast_source(datamodule)
        if source is None:
            return cls(touch_radii), "no training split to fit them on (not a ForecastDataSource)"
        setting, reason = fit_setting_baselines(source.training_trajectories(), source.fitted_baselines())
        return cls(touch_radii, setting), reason

    def rmse(self, item: RolloutItem) -> dict[str, Tensor]:
        """Per-step RMSE ``[T+1]`` (mm, ply nodes) of every baseline on ``item``'s trajectory, by name."""
        traj, hierarchy = item.trajectory, item.hierarchy
        out = {"static": rollout_rmse(rollout(static_plies, traj, hierarchy), traj.pos, traj.ply_mask)}
        for radius in self.touch_radii:
            rigid = rollout(RigidWithPunch(radius), traj, hierarchy)
            out[f"rigid_r{radius:g}"] = rollout_rmse(rigid, traj.pos, traj.ply_mask)
        for name, baseline in self.setting_baselines.items():
            try:
                out[name] = rollout_rmse(baseline.predict(traj), traj.pos, traj.ply_mask)
            except UnplaceablePart as err:
                self.refused.setdefault(name, str(err))
                out[name] = torch.full_like(out["static"], float("nan"))
        return out
