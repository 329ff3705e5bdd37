"""Pictures of a design study: where on the plies, over which settings, how well predicted.

:func:`measure_field` gives a measure's field (the per-node or per-cell values behind the
scalar of :func:`~torch_ampn.design.measures.part_quality`) on each ply, at the formed
positions; :func:`plot_measure_maps` draws it in plan view, one column per ply and one row per
rollout (e.g. predicted and simulated), on one colour scale. :func:`plot_parameter_map` draws
:func:`~torch_ampn.design.search.parameter_map`; :func:`plot_verification` a
:class:`~torch_ampn.design.verify.Verification`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.design.measures import (
    MEASURES,
    WrinkleOperator,
    draw_in_field,
    penetration_field,
    ply_components,
    shear_field,
)
from torch_ampn.design.verify import Verification

#: The field behind each scalar measure, its label and whether it is signed.
FIELDS: dict[str, tuple[str, bool]] = {
    "wrinkle": ("out-of-plane waviness [mm]", True),
    "draw_in": ("draw-in [mm]", True),
    "shear": ("in-plane shear angle [deg]", True),
    "penetration": ("tool penetration [mm]", False),
}


def field_of(measure: str) -> str:
    """The field of a scalar measure: ``"wrinkle_rms"`` -> ``"wrinkle"``."""
    if measure not in MEASURES:
        raise ValueError(f"unknown measure {measure!r}; choose from {sorted(MEASURES)}")
    return next(f for f in FIELDS if measure.startswith(f))


def measure_field(
    traj: Trajectory, pos: Tensor, field: str, wrinkle: WrinkleOperator | None = None
) -> list[tuple[Tensor, Tensor]]:
    """A field on each ply at positions ``pos`` ``[N, 3]``: per ply ``(points [M, 3], values [M])``.

    ``points`` are the formed positions of the ply's nodes (``wrinkle``, ``penetration``), of
    its free-edge nodes (``draw_in``) or of its cell centroids (``shear``); float64.
    """
    if field not in FIELDS:
        raise ValueError(f"unknown field {field!r}; choose from {sorted(FIELDS)}")
    x = pos.double()
    out = []
    if field in ("wrinkle", "penetration"):
        if field == "wrinkle":
            if wrinkle is None or not wrinkle.applies_to(traj):
                wrinkle = WrinkleOperator(traj)
            values = wrinkle(pos)
        else:
            values = penetration_field(traj, pos)
        for c in ply_components(traj):
            nodes = ((traj.component == c) & (traj.node_type == NodeType.PLY)).nonzero().squeeze(1)
            out.append((x[nodes], values[nodes]))
    elif field == "draw_in":
        nodes, values = draw_in_field(traj, pos)
        comp = traj.component[nodes]
        for c in ply_components(traj):
            keep = comp == c
            out.append((x[nodes[keep]], values[keep]))
    else:
        comps, values = shear_field(traj, pos)
        for c in ply_components(traj):
            keep = comps == c
            out.append((x[traj.cells[c]].mean(1), values[keep]))
    return out


def plot_measure_maps(
    path: str | Path, traj: Trajectory, rollouts: Mapping[str, Tensor], measure: str, title: str = ""
) -> Path:
    """Plan-view maps of ``measure``'s field on each ply (columns) for each final state (rows).

    Args:
        path: The PNG to write.
        traj: The part.
        rollouts: Row label -> positions ``[N, 3]`` (e.g. ``{"predicted": ..., "simulated": ...}``).
        measure: A scalar measure's name (its field is drawn) or a field's name.
        title: Above the figure.
    """
    import matplotlib.pyplot as plt

    field = measure if measure in FIELDS else field_of(measure)
    label, signed = FIELDS[field]
    wrinkle = WrinkleOperator(traj) if field == "wrinkle" else None
    maps = {row: measure_field(traj, pos, field, wrinkle) for row, pos in rollouts.items()}
    values = torch.cat([v for plies in maps.values() for _, v in plies])
    top = float(values.abs().max()) if values.numel() else 1.0
    top = top if top > 0 else 1.0
    vmin, vmax = (-top, top) if signed else (0.0, top)
    cmap = "RdBu_r" if signed else "viridis"
    rows, cols = len(maps), max(len(p) for p in maps.values())
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols + 1.0, 2.5 * rows), squeeze=False)
    scatter = None
    for i, (row, plies) in enumerate(maps.items()):
        for j, (points, v) in enumerate(plies):
            ax = axes[i, j]
            scatter = ax.scatter(points[:, 0], points[:, 1], c=v, s=6, cmap=cmap, vmin=vmin, vmax=vmax)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"ply {j + 1}")
            if j == 0:
                ax.set_ylabel(row)
    if scatter is not None:
        fig.colorbar(scatter, ax=axes.ravel().tolist(), label=label, shrink=0.9)
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_parameter_map(
    path: str | Path, grid: dict, best: np.ndarray, axes: tuple[int, int], label: str
) -> None:
    """Contours of :func:`~torch_ampn.design.search.parameter_map`'s grid, the best setting marked."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    c = ax.contourf(grid["a"], grid["b"], grid["values"].T, levels=16, cmap="viridis")
    fig.colorbar(c, ax=ax, label=label)
    ax.plot(best[axes[0]], best[axes[1]], "r*", ms=14, label="best")
    ax.set_xlabel(grid["axes"][0])
    ax.set_ylabel(grid["axes"][1])
    ax.legend(loc="upper right")
    ax.set_title("predicted measure, other settings at the best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_verification(path: str | Path, check: Verification, label: str) -> None:
    """Predicted against simulated measure of the random settings and the chosen one; Spearman per measure."""
    import matplotlib.pyplot as plt

    fig, (ax, bars) = plt.subplots(1, 2, figsize=(10.0, 4.5), gridspec_kw={"width_ratios": [1, 1.1]})
    if check.runs > 1:  # the spread of the runs: the chaos left in each simulated point
        spread = check.run_objective[:, 1:].std(axis=0)  # [N]
        ax.errorbar(
            check.random_simulated, check.random_predicted, xerr=spread, fmt="none", ecolor="0.7", lw=0.8
        )
    runs = f" (mean of {check.runs} runs)" if check.runs > 1 else ""
    ax.scatter(check.random_simulated, check.random_predicted, s=18, label="random settings" + runs)
    ax.scatter([check.chosen_simulated], [check.chosen_predicted], c="r", marker="*", s=160, label="chosen")
    lim = [
        min(check.random_simulated.min(), check.random_predicted.min(), check.chosen_simulated),
        max(check.random_simulated.max(), check.random_predicted.max(), check.chosen_simulated),
    ]
    ax.plot(lim, lim, "k--", lw=0.8)
    ax.set_xlabel(f"simulated {label}")
    ax.set_ylabel(f"predicted {label}")
    ax.set_title(
        f"Spearman {check.spearman:.2f}, chosen ranks {check.rank} of {len(check.random_simulated) + 1}"
    )
    ax.legend()
    names = list(check.spearman_by_measure)
    at = np.arange(len(names))
    rho = [np.nan_to_num(check.spearman_by_measure[n]) for n in names]
    bars.barh(at + (0.2 if check.repeat else 0), rho, height=0.4, label="predicted vs simulated")
    if check.repeat:
        again = [np.nan_to_num(check.repeat_spearman_by_measure[n]) for n in names]
        bars.barh(at - 0.2, again, height=0.4, color="0.6", label=f"one run vs another ({check.repeat:g} mm)")
        ceiling = [check.spearman_ceiling(n) for n in names]
        bars.scatter(ceiling, at + 0.2, marker="|", s=200, c="k", label="chaos-free predictor, about")
    bars.set_yticks(at, names)
    bars.axvline(0, color="k", lw=0.8)
    bars.set_xlim(-1, 1)
    bars.set_xlabel(f"Spearman over {len(check.random_simulated)} random settings")
    bars.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


__all__ = [
    "FIELDS",
    "field_of",
    "measure_field",
    "plot_measure_maps",
    "plot_parameter_map",
    "plot_verification",
]
