"""How much the process settings move the part, against how chaotic the forming is.

A surrogate can only learn what the settings change. Two numbers tell whether a dataset holds
such an effect:

* the **setting spread**: the rollout RMSE of each trajectory against the dataset's mean
  trajectory (what ignoring the settings costs), and between pairs of trajectories;
* the **chaos floor**: the rollout RMSE between a trajectory and the same settings simulated
  again from initial ply positions moved by ``perturbation`` (1e-6 mm): no predictor of the
  settings can be expected to do better than that.

The RMSE is the models' metric (:func:`~torch_ampn.rollout.rollout_rmse` over ply nodes,
averaged over the steps ``1 .. T``), in mm.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from typing import Any

import torch

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.sim.config import StampFormingConfig

#: The aims of a dataset whose settings matter: spread at least this many times the chaos
#: floor, and at least this many mm.
SPREAD_OVER_FLOOR, SPREAD_MM = 10.0, 1.0
#: A blown-up run: a ply node farther from its start than this many times the tools' travel
#: (healthy coarse runs of the default part: at most 0.9, the dome's depth; draw-in adds little),
#: or moving within one saved step more than this fraction of it beyond the tools' own motion in
#: a saved step (healthy, 50 steps: at most 0.4, a free corner fluttering; the punch moves 0.02
#: per step; with 6 saved steps it moves 0.17 per step and a node draped over the die's edge
#: 0.56).
BLOWN_UP_TRAVEL, BLOWN_UP_STEP = 1.25, 0.5


def _largest_motions(traj: Trajectory) -> tuple[float, float, float, float]:
    """Largest motions (mm): ply node in a step, ply node from its start, tool from start, tool in a step."""
    moved = (traj.pos - traj.pos[0]).norm(dim=-1)  # [T+1, N]
    steps = (traj.pos[1:] - traj.pos[:-1]).norm(dim=-1)  # [T, N]
    step, tool_step = steps[:, traj.ply_mask], steps[:, ~traj.ply_mask]
    tools = moved[:, ~traj.ply_mask]
    return (
        float(step.max()) if step.numel() else 0.0,
        float(moved[:, traj.ply_mask].max()),
        float(tools.max()) if tools.numel() else 0.0,
        float(tool_step.max()) if tool_step.numel() else 0.0,
    )


def _blown_up(step: float, moved: float, travel: float, tool_step: float) -> str | None:
    if travel <= 0:
        return None
    if moved > BLOWN_UP_TRAVEL * travel:
        return f"a ply node ends {moved:.0f} mm from its start (the tools travel {travel:.0f} mm)"
    if step > BLOWN_UP_STEP * travel + tool_step:
        return (
            f"a ply node moves {step:.0f} mm within one saved step (the tools travel {travel:.0f} mm, "
            f"{tool_step:.1f} mm in a step)"
        )
    return None


def blow_up(traj: Trajectory) -> str | None:
    """Why ``traj`` looks blown up (:data:`BLOWN_UP_TRAVEL`, :data:`BLOWN_UP_STEP`), or ``None``.

    A run is blown up when a ply node ends up farther from its start than ``BLOWN_UP_TRAVEL``
    times the farthest tool node's travel, or moves within one saved step more than
    ``BLOWN_UP_STEP`` times that travel plus the tools' largest motion in a saved step.
    Trajectories whose tools stay put are never flagged.
    """
    return _blown_up(*_largest_motions(traj))


def trajectory_rmse(a: Trajectory | torch.Tensor, b: Trajectory) -> float:
    """Rollout RMSE (mm) of ``a`` (a trajectory or positions ``[T+1, N, 3]``) against ``b``, ply nodes."""
    from torch_ampn.rollout import rollout_rmse

    pos = a.pos if isinstance(a, Trajectory) else a
    return float(rollout_rmse(pos, b.pos, b.ply_mask)[1:].mean())


def _one_mesh(trajectories: Sequence[Trajectory]) -> None:
    first = trajectories[0]
    for t in trajectories[1:]:
        if t.pos.shape != first.pos.shape or not torch.equal(t.component, first.component):
            raise ValueError(
                f"{t.meta.get('name', 'a trajectory')}: field 'pos' has another mesh than "
                f"{first.meta.get('name', 'the first')}'s: the spread needs trajectories of one mesh"
            )


def setting_spread(trajectories: Sequence[Trajectory]) -> dict[str, Any]:
    """Spread of ``trajectories`` (one mesh, at least 2) over their settings.

    Returns:
        ``from_mean``: per-trajectory RMSE against the mean trajectory (``mean``, ``std``,
        ``values``); ``pairs``: RMSE between consecutive trajectories (0-1, 2-3, ...: pairs of
        independent random settings), same keys; ``max_step_mm`` and ``max_displacement_mm``:
        the largest motion of any ply node in one saved step and from its start (sanity
        checks: a spread made by a solver blowing up is no setting effect; the punch moves
        ``stroke`` in all, ``stroke / num_steps`` per step).
    """
    trajectories = list(trajectories)
    if len(trajectories) < 2:
        raise ValueError(f"the setting spread needs at least 2 trajectories, got {len(trajectories)}")
    _one_mesh(trajectories)
    mean = torch.stack([t.pos.double() for t in trajectories]).mean(0)  # [T+1, N, 3]
    from_mean = [trajectory_rmse(mean, t) for t in trajectories]
    pairs = [trajectory_rmse(a, b) for a, b in zip(trajectories[0::2], trajectories[1::2], strict=False)]
    step, moved, travel, tool_step = zip(*(_largest_motions(t) for t in trajectories), strict=True)
    return {
        "trajectories": len(trajectories),
        "from_mean": _summary(from_mean),
        "pairs": _summary(pairs),
        "max_step_mm": max(step),
        "max_displacement_mm": max(moved),
        "tool_travel_mm": max(travel),
        "tool_step_mm": max(tool_step),
    }


def rerun_perturbed(
    trajectories: Sequence[Trajectory],
    perturbation: float = 1e-6,
    compile: bool = False,
    device: torch.device | str = "cpu",
) -> list[Trajectory]:
    """Each trajectory's settings simulated again from a start moved by up to ``perturbation`` mm.

    Each is simulated from its ``meta`` (``config`` and ``seed``), one at a time, eagerly unless
    ``compile`` (a compiled solver's last bits also depend on the batch; eager ones do not, so
    eagerly the difference is the perturbation's effect alone).
    """
    from torch_ampn.sim.simulate import sample_process, simulate_batch

    again = []
    for traj in trajectories:
        if traj.meta.get("simulator") != "torch_ampn.sim" or "seed" not in traj.meta:
            raise ValueError(
                f"{traj.meta.get('name', 'a trajectory')}: field 'meta' does not name the embedded "
                "simulator's config and seed: the chaos floor simulates it again"
            )
        cfg = StampFormingConfig.from_dict(traj.meta["config"])
        settings, where = None, traj.meta.get("gripper_edge_fraction")
        if where is not None and sample_process(cfg, int(traj.meta["seed"]))[0].tolist() != where:
            settings = [(where, traj.gripper_force.double())]  # explicit settings, not the seed's
        again += simulate_batch(
            cfg,
            [int(traj.meta["seed"])],
            compile=compile,
            device=device,
            perturbation=perturbation,
            settings=settings,
        )
    return again


def chaos_floor(
    trajectories: Sequence[Trajectory],
    perturbation: float = 1e-6,
    compile: bool = False,
    device: torch.device | str = "cpu",
    again: Sequence[Trajectory] | None = None,
) -> dict[str, Any]:
    """RMSE between each trajectory and its settings simulated again from a perturbed start.

    ``again``: those runs (:func:`rerun_perturbed`), if made before; else they are simulated here.
    """
    if again is None:
        again = rerun_perturbed(trajectories, perturbation, compile, device)
    values = [trajectory_rmse(b, a) for a, b in zip(trajectories, again, strict=True)]
    return {"perturbation_mm": perturbation, **_summary(values)}


#: The part-quality measures whose two-run reliability :func:`two_run_reliability` reports.
RELIABILITY_MEASURES: tuple[str, ...] = (
    "draw_in_mean",
    "wrinkle_rms",
    "wrinkle_amplitude",
    "shear_rms",
    "penetration_max",
)
#: The aims: Spearman between two runs of each setting (draw-in mean; wrinkle and shear RMS),
#: and the wrinkle RMS's spread between settings over its spread within a setting.
RELIABILITY_AIMS: dict[str, float] = {
    "draw_in_mean": 0.9,
    "wrinkle_rms": 0.7,
    "shear_rms": 0.7,
    "wrinkle_between_over_within": 3.0,
}


def two_run_reliability(
    first: Sequence[Trajectory], second: Sequence[Trajectory], measures: Sequence[str] = RELIABILITY_MEASURES
) -> dict[str, Any]:
    """Do two runs of each setting agree on the part's quality, and on its ranking over the settings?

    ``first[i]`` and ``second[i]`` are two runs of one setting (e.g. from starts 1e-6 mm apart,
    :func:`rerun_perturbed`); at least 3 settings. For each measure of
    :func:`torch_ampn.design.measures.part_quality` at the final state: the values of both runs,
    ``spearman`` (rank correlation of the two runs over the settings: how reliably the data
    rank the settings), ``between`` (standard deviation over the settings of the mean of the two
    runs), ``within`` (the standard deviation within a setting, ``sqrt(mean((a - b)^2) / 2)``),
    their ratio, and ``range`` (largest minus smallest over the settings). ``chaos_mm``: the
    rollout RMSE between the two runs, mean over the settings.
    """
    from scipy.stats import spearmanr

    from torch_ampn.design.measures import WrinkleOperator, part_quality

    if len(first) != len(second) or len(first) < 3:
        raise ValueError(f"two runs of at least 3 settings needed, got {len(first)} and {len(second)}")
    _one_mesh([*first, *second])
    wrinkle = WrinkleOperator(first[0])
    values = {
        run: [part_quality(t, t.pos[-1].double(), wrinkle=wrinkle, names=measures) for t in runs]
        for run, runs in (("first", first), ("second", second))
    }
    out: dict[str, Any] = {
        "settings": len(first),
        "chaos_mm": _summary([trajectory_rmse(b, a) for a, b in zip(first, second, strict=True)]),
        "measures": {},
    }
    for name in measures:
        a = torch.tensor([v[name] for v in values["first"]], dtype=torch.float64)
        b = torch.tensor([v[name] for v in values["second"]], dtype=torch.float64)
        mean = 0.5 * (a + b)
        between = float(mean.std(correction=0))
        within = float(((a - b).square().mean() / 2).sqrt())
        rho = spearmanr(a.numpy(), b.numpy()).statistic
        out["measures"][name] = {
            "first": a.tolist(),
            "second": b.tolist(),
            "spearman": float(rho) if math.isfinite(rho) else float("nan"),
            "between": between,
            "within": within,
            "between_over_within": between / within if within > 0 else math.inf,
            "range": float(mean.max() - mean.min()),
        }
    m = out["measures"]
    checks = [m[k]["spearman"] >= v for k, v in RELIABILITY_AIMS.items() if k in m]
    if "wrinkle_rms" in m:
        checks.append(
            m["wrinkle_rms"]["between_over_within"] >= RELIABILITY_AIMS["wrinkle_between_over_within"]
        )
    out["aims"] = dict(RELIABILITY_AIMS)
    out["meets_aims"] = bool(all(checks))
    return out


def format_reliability(report: dict[str, Any]) -> str:
    """A small table of :func:`two_run_reliability`'s result."""
    lines = [
        f"two runs of {report['settings']} settings: rollout RMSE between them "
        f"{report['chaos_mm']['mean']:.3f} mm",
        f"{'measure':<18} {'spearman':>8} {'between':>8} {'within':>8} {'ratio':>6} {'range':>8}",
    ]
    for name, r in report["measures"].items():
        lines.append(
            f"{name:<18} {r['spearman']:8.2f} {r['between']:8.3f} {r['within']:8.3f} "
            f"{r['between_over_within']:6.1f} {r['range']:8.3f}"
        )
    aims = ", ".join(f"{k} >= {v:g}" for k, v in report["aims"].items())
    lines.append(f"aims ({aims}): {'met' if report['meets_aims'] else 'not met'}")
    return "\n".join(lines)


def spread_report(spread: dict[str, Any], floor: dict[str, Any]) -> dict[str, Any]:
    """The spread against the floor: their ratio, and whether the aims are met.

    The aims: :data:`SPREAD_OVER_FLOOR` and :data:`SPREAD_MM`, and no blow-up (``blown_up``: a
    ply node farther from its start than :data:`BLOWN_UP_TRAVEL` times the farthest tool node's
    travel, or moving more than :data:`BLOWN_UP_STEP` times that travel within one saved step).
    """
    s, f = spread["from_mean"]["mean"], floor["mean"]
    ratio = s / f if f > 0 else math.inf
    # a ply node carried farther than the tools go, or jumping half their travel in one step
    blown_up = (
        _blown_up(
            spread["max_step_mm"],
            spread["max_displacement_mm"],
            spread["tool_travel_mm"],
            spread.get("tool_step_mm", 0.0),
        )
        is not None
    )
    return {
        **spread,
        "chaos_floor": floor,
        "spread_over_floor": ratio,
        "blown_up": bool(blown_up),
        "aims": {"spread_over_floor": SPREAD_OVER_FLOOR, "spread_mm": SPREAD_MM},
        "meets_aims": bool(ratio >= SPREAD_OVER_FLOOR and s >= SPREAD_MM and not blown_up),
    }


def format_report(report: dict[str, Any]) -> str:
    """A few lines of text for :func:`spread_report`'s result."""
    m, p, f = report["from_mean"], report["pairs"], report["chaos_floor"]
    return "\n".join(
        [
            f"trajectories: {report['trajectories']}",
            f"spread, RMSE from the mean trajectory: {m['mean']:.3f} +- {m['std']:.3f} mm",
            f"spread, RMSE between pairs of settings: {p['mean']:.3f} +- {p['std']:.3f} mm "
            f"({p['count']} pairs)",
            f"chaos floor, same settings from a start moved by {f['perturbation_mm']:g} mm: "
            f"{f['mean']:.4f} +- {f['std']:.4f} mm ({f['count']} trajectories)",
            f"largest motion of a ply node: {report['max_step_mm']:.1f} mm in one saved step, "
            f"{report['max_displacement_mm']:.1f} mm from its start (the tools travel "
            f"{report['tool_travel_mm']:.1f} mm)"
            + (": BLOWN UP, the spread is no setting effect" if report["blown_up"] else ""),
            f"spread / floor: {report['spread_over_floor']:.1f} (aims: >= {SPREAD_OVER_FLOOR:g}, "
            f"spread >= {SPREAD_MM:g} mm: {'met' if report['meets_aims'] else 'not met'})",
        ]
    )


def _summary(values: list[float]) -> dict[str, Any]:
    return {
        "mean": statistics.fmean(values),
        "std": statistics.pstdev(values) if len(values) > 1 else 0.0,
        "count": len(values),
        "values": values,
    }
