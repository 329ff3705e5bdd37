"""How far more training trajectories take the classical design-study surrogate (POD + GP).

    python benchmarks/learning_curve.py data/settings --out benchmarks/results/settings/learning_curve.json

Fits :class:`torch_ampn.baselines.PODRegression` (POD + Gaussian process) on random subsets of
the training split of growing size (``--sizes``, ``--repeats`` subsets each; the whole split
once) and rolls it out on the test split. The curve ``RMSE(n)^2 = e^2 + b n^-c`` (scipy's
``curve_fit``) extrapolates to the paper's 684 training trajectories and to no limit (``e``).
Two floors beside it: the POD basis's own (each test trajectory projected on the basis of the
whole training split: what the best coefficients would reach) and the chaos floor of
``torch-ampn-data spread --chaos`` (the RMS distance of two runs of the same settings; a
predictor of their mean errs by at least that over sqrt 2 against one run). Prints a table,
writes JSON and a plot.

``--direct benchmarks/results/direct/table.json`` puts the direct model's runs of
``benchmarks/direct.py`` beside it (the rows of each ``--direct-variant``: mean and spread over
seeds, one series per training-step count, the same curve fitted where a series has three sizes
or more); those runs took the *first* ``n`` training trajectories, POD + GP random subsets.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
from pathlib import Path

import numpy as np
import torch

from torch_ampn.baselines import PODRegression
from torch_ampn.data import TrajectoryDataset
from torch_ampn.rollout import rollout_rmse
from torch_ampn.utils.io import atomic_write_text


def test_rmse(model: PODRegression, test: list) -> float:
    """Mean rollout RMSE (mm, ply nodes, steps 1..T) of ``model`` on ``test``."""
    return float(np.mean([float(rollout_rmse(model.predict(t), t.pos, t.ply_mask)[1:].mean()) for t in test]))


def basis_floor(model: PODRegression, test: list) -> float:
    """Mean rollout RMSE of each test trajectory projected on ``model``'s POD basis (best coefficients)."""
    rmse = []
    for t in test:
        ply = t.pos[:, t.ply_mask].double()  # [T+1, P, 3]
        centred = ply.reshape(-1).numpy() - model._mean  # [D]
        projected = model._mean + (centred @ model._basis.T) @ model._basis
        pred = t.pos.clone().float()
        pred[:, t.ply_mask] = torch.from_numpy(projected).float().reshape(ply.shape)
        rmse.append(float(rollout_rmse(pred, t.pos, t.ply_mask)[1:].mean()))
    return float(np.mean(rmse))


def fit_curve(sizes: list[int], rmse: list[float]) -> dict:
    """``RMSE^2 = e^2 + b n^-c`` fitted to the points; its parameters and extrapolations."""
    from scipy.optimize import curve_fit

    n, y = np.asarray(sizes, float), np.asarray(rmse, float) ** 2

    def model(n, e2, b, c):
        return e2 + b * n ** (-c)

    (e2, b, c), _ = curve_fit(model, n, y, p0=(y.min() / 2, y.max() * n.min(), 1.0), bounds=(0, np.inf))
    return {"e_mm": math.sqrt(e2), "b": b, "c": c, "at_684": math.sqrt(model(684.0, e2, b, c))}


def curve_rmse(curve: dict, n: np.ndarray) -> np.ndarray:
    """RMSE of the fitted curve ``sqrt(e^2 + b n^-c)`` at sizes ``n``."""
    return np.sqrt(curve["e_mm"] ** 2 + curve["b"] * n ** (-curve["c"]))


def write(out: Path, result: dict) -> None:
    """The result as JSON at ``out`` and its plot beside it."""
    atomic_write_text(out, json.dumps(result, indent=1))
    plot(out.with_suffix(".png"), result)
    print(f"wrote {out} and {out.with_suffix('.png')}")


def direct_series(table: Path, variant: str) -> list[dict]:
    """A direct variant's test RMSE per training-step count: ``[{variant, steps, points, curve?}]``."""
    rows = [r for r in json.loads(table.read_text())["rows"] if r["variant"] == variant]
    if not rows:
        raise ValueError(f"{table}: field 'rows' has no run of variant {variant!r}")
    series = []
    for steps in sorted({r["steps"] for r in rows}):
        points = sorted((r for r in rows if r["steps"] == steps), key=lambda r: r["train"])
        entry: dict = {
            "variant": variant,
            "steps": steps,
            "points": [
                {
                    "n": r["train"],
                    "rmse_mean": r["rmse_mm_mean"],
                    "rmse_std": r["rmse_mm_std"],
                    "seeds": r["seeds"],
                }
                for r in points
            ],
        }
        if len(points) >= 3:
            entry["curve"] = fit_curve([r["train"] for r in points], [r["rmse_mm_mean"] for r in points])
        series.append(entry)
    return series


#: Legend names of the variants of ``benchmarks/direct.py`` (others: their own name).
VARIANT_NAMES = {"direct_ampn": "direct model", "direct_ampn-prior": "direct model on POD + GP"}


def series_label(series: dict) -> str:
    """``direct model, 2,000 steps``: the variant's legend name and the series' step count."""
    variant = series.get("variant", "direct_ampn")
    return f"{VARIANT_NAMES.get(variant, variant)}, {series['steps']:,} steps"


def report_direct(direct: list[dict]) -> None:
    """Print the direct variants' series."""
    for series in direct:
        text = ", ".join(f"{p['n']}: {p['rmse_mean']:.3f}" for p in series["points"])
        fit = f"; levels off at {series['curve']['e_mm']:.3f} mm" if "curve" in series else ""
        print(f"{series_label(series)}: {text} mm{fit}")


def plot(path: Path, result: dict) -> None:
    """RMSE against training trajectories, the fitted curve and the floors."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for k, row in enumerate(result["points"]):
        label = "POD + GP (random subsets)" if k == 0 else None
        ax.plot([row["n"]] * len(row["rmse"]), row["rmse"], "o", color="C0", alpha=0.6, label=label)
    curve = result["curve"]
    n = np.geomspace(min(r["n"] for r in result["points"]), 800, 100)
    ax.plot(n, curve_rmse(curve, n), "-", color="C0", label="its fit")
    for k, series in enumerate(result.get("direct", [])):
        color = f"C{4 + k}"
        xs = [p["n"] for p in series["points"]]
        ax.errorbar(
            xs, [p["rmse_mean"] for p in series["points"]], yerr=[p["rmse_std"] for p in series["points"]],
            fmt="s", color=color, label=series_label(series),
        )  # fmt: skip
        if "curve" in series:
            m = np.geomspace(min(xs), 800, 100)
            ax.plot(m, curve_rmse(series["curve"], m), "--", color=color)
    ax.axhline(result["basis_floor_mm"], color="C2", ls="--", label="POD basis floor")
    if result.get("chaos_floor_mm"):
        ax.axhline(result["chaos_floor_mm"] / math.sqrt(2), color="C3", ls=":", label="chaos floor / sqrt 2")
    ax.set_xscale("log")
    ax.set_xticks([24, 48, 96, 192, 384, 768], ["24", "48", "96", "192", "384", "768"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("training trajectories")
    ax.set_ylabel("test rollout RMSE [mm]")
    ax.set_title("POD + GP on the settings" + (" and the direct model" if result.get("direct") else ""))
    ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 0.12))
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=110)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, fit, print and write."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--sizes", type=int, nargs="+", default=[24, 48, 96])
    parser.add_argument("--repeats", type=int, default=3, help="random subsets per size")
    parser.add_argument("--spread", type=Path, default=None, help="JSON of torch-ampn-data spread --chaos")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--direct", type=Path, default=None, help="table.json of benchmarks/direct.py")
    parser.add_argument("--direct-variant", nargs="+", default=["direct_ampn"], help="variants to draw")
    parser.add_argument(
        "--replot", action="store_true", help="keep --out's POD + GP points; redo the direct series and plot"
    )
    args = parser.parse_args(argv)
    direct = [s for v in args.direct_variant for s in direct_series(args.direct, v)] if args.direct else []
    if args.replot:
        result = json.loads(args.out.read_text())
        result["direct"] = direct
        report_direct(direct)
        write(args.out, result)
        return 0
    train = list(TrajectoryDataset(args.data_dir, "train", max_cached_mb=0))
    test = list(TrajectoryDataset(args.data_dir, "test", max_cached_mb=0))
    rng = np.random.default_rng(0)
    points = []
    for n in [s for s in args.sizes if s < len(train)]:
        subsets = [rng.choice(len(train), n, replace=False) for _ in range(args.repeats)]
        rmse = [test_rmse(PODRegression().fit([train[i] for i in s]), test) for s in subsets]
        points.append({"n": n, "rmse": rmse})
        print(f"{n:>4} training trajectories: POD + GP {np.mean(rmse):.3f} mm ({len(rmse)} subsets)")
    full = PODRegression().fit(train)
    points.append({"n": len(train), "rmse": [test_rmse(full, test)]})
    print(f"{len(train):>4} training trajectories: POD + GP {points[-1]['rmse'][0]:.3f} mm", flush=True)
    sizes = [p["n"] for p in points for _ in p["rmse"]]
    values = [v for p in points for v in p["rmse"]]
    result = {
        "date": datetime.date.today().isoformat(),
        "dataset": str(args.data_dir),
        "test": len(test),
        "points": points,
        "curve": fit_curve(sizes, values),
        "basis_floor_mm": basis_floor(full, test),
        "basis_components": int(full._basis.shape[0]),
    }
    if args.spread:
        result["chaos_floor_mm"] = json.loads(args.spread.read_text())["chaos_floor"]["mean"]
    if direct:
        result["direct"] = direct
        report_direct(direct)
    curve = result["curve"]
    print(
        f"fit RMSE^2 = e^2 + b n^-c: e = {curve['e_mm']:.3f} mm, c = {curve['c']:.2f}; "
        f"at 684 trajectories {curve['at_684']:.3f} mm; POD basis floor {result['basis_floor_mm']:.3f} mm "
        f"({result['basis_components']} components)"
        + (f"; chaos floor {result['chaos_floor_mm']:.3f} mm" if "chaos_floor_mm" in result else "")
    )
    write(args.out, result)
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
