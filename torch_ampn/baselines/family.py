"""Setting-aware baselines across a family of parts: one per ply count, on settings and part.

A family dataset (:class:`~torch_ampn.sim.PartFamily`) gives every trajectory its own tool
geometry and ply stack. Parts with the same number of plies share the plies' mesh (the flat
laminate) and differ in their tools, so a parametric surrogate can follow the family on the
plies' nodes with the part's parameters as more inputs beside the process settings: MMGP's idea
(Casenave, Staber and Roynard, NeurIPS 2023) with the identity as the morphing. :class:`PerPlyCount` fits one
:class:`~torch_ampn.baselines.settings.TrajectoryBaseline` per ply count on
:func:`~torch_ampn.baselines.process_settings` and :func:`part_parameters`; :func:`family_baselines` gives the
reported ones (the mean per ply count, the nearest training part, a linear regression and
POD + GP on settings and part). A part of a shape or ply count that no training part had is
refused in one line: no parametric surrogate can place it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torch_ampn.baselines.settings import (
    SETTING_BASELINE_NAMES,
    MeanTrajectory,
    NearestSetting,
    PODRegression,
    TrajectoryBaseline,
)
from torch_ampn.data.trajectory import Trajectory


class UnplaceablePart(ValueError):
    """A part of a ply count or tool shape that no training part had.

    No parametric surrogate can place it (a family's test set beyond its ranges).
    """


#: The tool-geometry entries of :func:`part_parameters`, in their order.
GEOMETRY_NAMES = ("dome_depth", "dome_axis_x", "dome_axis_y", "dome_centre", "dome_flat_top", "dome_exponent")


def _part(traj: Trajectory) -> dict:
    part = traj.meta.get("part")
    if part is None:
        name = traj.meta.get("name", "trajectory")
        raise ValueError(f"{name}: meta has no 'part' (the tool and stack of a family's trajectory)")
    return part


def num_plies(traj: Trajectory) -> int:
    """The plies of ``traj``'s part (its ``meta["part"]["ply_angles"]``)."""
    return len(_part(traj)["ply_angles"])


def part_parameters(traj: Trajectory) -> Tensor:
    r"""The parameters of ``traj``'s part, ``[6 + 2 n]`` float64 for ``n`` plies.

    The tool geometry (:data:`GEOMETRY_NAMES`: depth, semi-axes and centre in mm, flat top as a
    fraction, footprint exponent, 2 for an elliptic dome), then every ply's fibre angle
    :math:`\theta` as :math:`\cos 2\theta` and :math:`\sin 2\theta` (a fibre at
    :math:`\theta` and at :math:`\theta + 180°` is the same fibre, so the angle enters doubled).

    Raises:
        ValueError: If ``traj`` records no part (``meta["part"]``, as family datasets do).
    """
    part = _part(traj)
    axes = part["dome_axes"]
    geometry = [
        part["dome_depth"], axes[0], axes[1], part["dome_centre"], part["dome_flat_top"],
        part.get("dome_exponent", 2.0),
    ]  # fmt: skip
    doubled = torch.tensor([2.0 * math.radians(a) for a in part["ply_angles"]], dtype=torch.float64)
    return torch.cat([torch.tensor(geometry, dtype=torch.float64), doubled.cos(), doubled.sin()])


def part_parameter_names(plies: int) -> list[str]:
    """Names of the entries of :func:`part_parameters` for a part of ``plies`` plies."""
    cos = [f"ply{p}_cos2theta" for p in range(plies)]
    return [*GEOMETRY_NAMES, *cos, *(f"ply{p}_sin2theta" for p in range(plies))]


class PerPlyCount:
    """One baseline per ply count of a family, on the process settings and the part's parameters.

    Args:
        make: Makes an unfitted baseline (e.g. ``lambda: PODRegression("gp")``); one is made and
            fitted per ply count, with :attr:`~TrajectoryBaseline.parts` set, so that its inputs
            are the process settings and :func:`part_parameters` and only the plies must share
            a mesh.

    Example:
        >>> pod_gp = PerPlyCount(lambda: PODRegression("gp")).fit(train)  # doctest: +SKIP
        >>> pos = pod_gp.predict(test[0])  # [T + 1, N, 3]; the tools' nodes are test[0]'s  # doctest: +SKIP
    """

    def __init__(self, make: Callable[[], TrajectoryBaseline]) -> None:
        self.make = make
        self.baselines: dict[int, TrajectoryBaseline] = {}
        self.shapes: dict[int, set[str]] = {}

    def fit(self, trajectories: Sequence[Trajectory]) -> PerPlyCount:
        """Fit one baseline per ply count on ``trajectories`` (a family's training parts); returns ``self``.

        A ply count with fewer than 2 training parts gets no baseline (its parts are refused).

        Raises:
            ValueError: If no ply count has 2 parts, or a trajectory records no part.
        """
        groups: dict[int, list[Trajectory]] = {}
        for traj in trajectories:
            groups.setdefault(num_plies(traj), []).append(traj)
        groups = {plies: group for plies, group in groups.items() if len(group) >= 2}
        if not groups:
            raise ValueError("PerPlyCount.fit needs at least 2 training parts of one ply count")
        self.baselines, self.shapes = {}, {}
        for plies, group in sorted(groups.items()):
            baseline = self.make()
            baseline.parts = True
            self.baselines[plies] = baseline.fit(group)
            self.shapes[plies] = {str(_part(t).get("shape", "")) for t in group}
        return self

    def _baseline_of(self, traj: Trajectory) -> TrajectoryBaseline:
        if not self.baselines:
            raise RuntimeError("PerPlyCount: call fit() first")
        name, plies = traj.meta.get("name", "trajectory"), num_plies(traj)
        shape = _part(traj).get("shape", "")
        if plies not in self.baselines:
            raise UnplaceablePart(
                f"{name}: a part of {plies} plies; the baselines were fitted on parts of "
                f"{sorted(self.baselines)} plies, and a parametric surrogate cannot place another stack"
            )
        if shape not in self.shapes[plies]:
            raise UnplaceablePart(
                f"{name}: a {shape!r} part; the {plies}-ply training parts were "
                f"{sorted(self.shapes[plies])}, and a parametric surrogate cannot place another tool shape"
            )
        return self.baselines[plies]

    def predict(self, traj: Trajectory) -> Tensor:
        """The predicted trajectory of ``traj``'s settings and part, ``[T+1, N, 3]`` (tools: ``traj``'s)."""
        return self._baseline_of(traj).predict(traj)

    def predict_many(self, trajectories: Sequence[Trajectory]) -> list[Tensor]:
        """:meth:`predict` of each trajectory (one batch per ply count), in their order."""
        trajs = list(trajectories)
        batches: dict[int, list[int]] = {}  # ply count -> indices of its trajectories
        for i, traj in enumerate(trajs):
            self._baseline_of(traj)  # refuses a part no baseline can place
            batches.setdefault(num_plies(traj), []).append(i)
        out: list[Tensor | None] = [None] * len(trajs)
        for plies, index in batches.items():
            predicted = self.baselines[plies].predict_many([trajs[i] for i in index])
            for i, pos in zip(index, predicted, strict=True):
                out[i] = pos
        return out

    def __repr__(self) -> str:
        made = next(iter(self.baselines.values()), None)
        return f"{type(self).__name__}({made!r}, ply counts {sorted(self.baselines)})"


def family_baselines() -> dict[str, PerPlyCount]:
    """The setting-aware baselines of a family, unfitted.

    By the names of :func:`~torch_ampn.baselines.setting_baselines`: the mean per ply count, the
    nearest training part, a linear regression and POD + GP on the settings and the part.
    """
    makers = (
        MeanTrajectory,
        NearestSetting,
        lambda: PODRegression("linear", num_components=None),
        lambda: PODRegression("gp"),
    )
    return {name: PerPlyCount(make) for name, make in zip(SETTING_BASELINE_NAMES, makers, strict=True)}


__all__ = [
    "GEOMETRY_NAMES",
    "PerPlyCount",
    "UnplaceablePart",
    "family_baselines",
    "num_plies",
    "part_parameter_names",
    "part_parameters",
]
