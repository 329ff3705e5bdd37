"""The next-step model's learning curve in training steps, from ``compare.py`` cells.

    python benchmarks/next_step_curve.py \\
        --cell "recipe=benchmarks/results/next_step_v3/steps_1000/ampn_seed0.json" \\
        --cell "recipe=benchmarks/results/compare_v3/ampn_seed0.json@2000" \\
        --cell "best lever=benchmarks/results/next_step_v3/mean_base_3k/ampn_seed0.json" \\
        --out benchmarks/results/next_step_v3/curve.json

Each ``--cell LABEL=PATH[@STEPS]`` is one point of the series ``LABEL``: a cell JSON of
``benchmarks/compare.py`` (its test RMSE, R² of the setting effect and fit seconds).
``@STEPS`` overrides the cell's step count, for cells tested with earlier weights than their last
(before 2026-12-07, a 3,000-step cell was tested with its step-2,000 weights). A series of two
step counts or more (``--min-points``: two early points, one taken half way down a learning-rate
schedule, extrapolate wildly) gets the power law ``RMSE = a steps^-c`` through its last two
points (log-log least squares over all points with ``--fit-all``), and the step count at which it would reach
the linear regression on the settings and the nearest training setting (the baselines in the
cells' JSON, built from the same training trajectories). Prints a table, writes JSON and a plot
(``--out`` with ``.png``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
from pathlib import Path

import numpy as np

from torch_ampn.utils.io import atomic_write_text

#: Baselines drawn as horizontal lines: the cells' JSON key and its label.
BASELINES = {
    "mean_trajectory_rmse": "mean training trajectory",
    "nearest_setting_rmse": "nearest training setting",
    "linear_settings_rmse": "linear regression on the settings",
    "pod_gp_rmse": "POD + GP",
}


def parse_cell(text: str) -> tuple[str, Path, int | None]:
    """``LABEL=PATH[@STEPS]`` -> ``(label, path, steps or None)``."""
    label, sep, rest = text.partition("=")
    if not sep or not label or not rest:
        raise argparse.ArgumentTypeError(f"--cell {text!r}: expected LABEL=PATH[@STEPS]")
    path, _, steps = rest.partition("@")
    return label, Path(path), int(steps) if steps else None


def read_point(path: Path, steps: int | None) -> dict:
    """One point of a series from a ``compare.py`` cell JSON."""
    try:
        cell = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise SystemExit(f"{path}: not a readable cell JSON ({error})") from None
    for field in ("rmse", "steps", "baselines"):
        if field not in cell:
            raise SystemExit(f"{path}: field {field!r} missing (not a compare.py cell)")
    return {
        "steps": steps if steps is not None else int(cell["steps"]),
        "rmse": float(cell["rmse"]),
        "r2": cell.get("setting_effect_r2"),
        # a point tested with earlier weights than the cell's last: its fit time is the longer fit's
        "fit_seconds": cell.get("fit_seconds") if steps is None else None,
        "seed": cell.get("seed"),
        "cell": str(path),
        "baselines": cell["baselines"],
    }


def power_law(points: list[dict], fit_all: bool = False, min_points: int = 2) -> dict | None:
    """``RMSE = a steps^-c`` through the last two points (or fitted to all); ``None`` below ``min_points``
    step counts (at least two)."""
    pts = sorted(points, key=lambda p: p["steps"])
    if len({p["steps"] for p in pts}) < max(2, min_points):
        return None
    used = pts if fit_all else pts[-2:]
    x = np.log([p["steps"] for p in used])
    y = np.log([p["rmse"] for p in used])
    slope, intercept = np.polyfit(x, y, 1)
    return {"a": float(math.exp(intercept)), "c": float(-slope), "points": len(used)}


def steps_to_reach(law: dict | None, target: float) -> float | None:
    """Training steps at which ``law`` reaches ``target`` mm; ``None`` if it does not fall."""
    if law is None or law["c"] <= 0:
        return None
    return float((law["a"] / target) ** (1.0 / law["c"]))


def main(argv: list[str] | None = None) -> int:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--cell", type=parse_cell, action="append", required=True, help="LABEL=PATH[@STEPS]")
    parser.add_argument("--out", type=Path, required=True, help="JSON; the plot beside it (.png)")
    parser.add_argument("--fit-all", action="store_true", help="fit the power law to every point")
    parser.add_argument(
        "--min-points", type=int, default=3, help="step counts a series needs for a power law (default 3)"
    )
    args = parser.parse_args(argv)

    series: dict[str, list[dict]] = {}
    for label, path, steps in args.cell:
        series.setdefault(label, []).append(read_point(path, steps))
    baselines = next(iter(series.values()))[0]["baselines"]
    result = {"date": datetime.date.today().isoformat(), "series": {}, "baselines": {}}
    for key, name in BASELINES.items():
        if key in baselines:
            result["baselines"][name] = float(baselines[key])

    linear = result["baselines"].get("linear regression on the settings")
    nearest = result["baselines"].get("nearest training setting")
    print("| series | steps | RMSE [mm] | R² | fit [s] |")
    print("|---|---:|---:|---:|---:|")
    for label, points in series.items():
        points.sort(key=lambda p: (p["steps"], p["seed"] or 0))
        law = power_law(points, args.fit_all, args.min_points)
        result["series"][label] = {
            "points": [{k: v for k, v in p.items() if k != "baselines"} for p in points],
            "power_law": law,
            "steps_to_linear_regression": steps_to_reach(law, linear) if linear else None,
            "steps_to_nearest_setting": steps_to_reach(law, nearest) if nearest else None,
        }
        for p in points:
            r2 = "" if p["r2"] is None else f"{p['r2']:.2f}"
            fit = "" if p["fit_seconds"] is None else f"{p['fit_seconds']:.0f}"
            print(f"| {label} (seed {p['seed']}) | {p['steps']:,} | {p['rmse']:.3f} | {r2} | {fit} |")
    for label, s in result["series"].items():
        if s["power_law"]:
            reach = s["steps_to_linear_regression"]
            where = f"{reach:,.0f} steps" if reach else "never (the error does not fall)"
            print(f"{label}: RMSE ~ steps^-{s['power_law']['c']:.2f}; the linear regression at {where}")
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    plot(result, args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


def plot(result: dict, path: Path) -> None:
    """RMSE against training steps (log-log), the power laws dashed, the baselines as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter

    fig, ax = plt.subplots(figsize=(7, 4.5))
    all_steps = [p["steps"] for s in result["series"].values() for p in s["points"]]
    lo, hi = min(all_steps) / 1.5, max(max(all_steps) * 4, 30000)
    for label, s in result["series"].items():
        steps = [p["steps"] for p in s["points"]]
        rmse = [p["rmse"] for p in s["points"]]
        (line,) = ax.plot(steps, rmse, "o-", label=label)
        law = s["power_law"]
        if law:
            x = np.geomspace(max(steps), hi, 20)
            ax.plot(x, law["a"] * x ** -law["c"], "--", color=line.get_color(), alpha=0.6)
    for (name, value), style in zip(result["baselines"].items(), [":", "-.", "--", "-"], strict=False):
        ax.axhline(value, color="grey", linestyle=style, linewidth=1)
        ax.text(hi, value, f" {name} {value:.2f}", va="center", fontsize=8, color="grey")
    ax.set(xscale="log", yscale="log", xlim=(lo, hi), xlabel="training steps", ylabel="test RMSE [mm]")
    ax.yaxis.set_major_formatter(FormatStrFormatter("%.2g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.2g"))
    ax.set_title(f"next-step AMPN on 32 unseen settings ({result['date']}); dashed: power law", fontsize=9)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
