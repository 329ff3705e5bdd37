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


def plot(path: Path, result: dict) -> None:
    """RMSE against training trajectories, the fitted curve and the floors."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for row in result["points"]:
        ax.plot([row["n"]] * len(row["rmse"]), row["rmse"], "o", color="C0", alpha=0.6)
    curve = result["curve"]
    n = np.geomspace(min(r["n"] for r in result["points"]), 800, 100)
    ax.plot(n, np.sqrt(curve["e_mm"] ** 2 + curve["b"] * n ** (-curve["c"])), "-", color="C0", label="fit")
    ax.axhline(result["basis_floor_mm"], color="C2", ls="--", label="POD basis floor")
    if result.get("chaos_floor_mm"):
        ax.axhline(result["chaos_floor_mm"] / math.sqrt(2), color="C3", ls=":", label="chaos floor / sqrt 2")
    ax.set_xscale("log")
    ax.set_xticks([24, 48, 96, 192, 384, 768], ["24", "48", "96", "192", "384", "768"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("training trajectories")
    ax.set_ylabel("test rollout RMSE [mm]")
    ax.set_title("POD + GP on the settings")
    ax.legend()
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
    args = parser.parse_args(argv)
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
    curve = result["curve"]
    print(
        f"fit RMSE^2 = e^2 + b n^-c: e = {curve['e_mm']:.3f} mm, c = {curve['c']:.2f}; "
        f"at 684 trajectories {curve['at_684']:.3f} mm; POD basis floor {result['basis_floor_mm']:.3f} mm "
        f"({result['basis_components']} components)"
        + (f"; chaos floor {result['chaos_floor_mm']:.3f} mm" if "chaos_floor_mm" in result else "")
    )
    atomic_write_text(args.out, json.dumps(result, indent=1))
    plot(args.out.with_suffix(".png"), result)
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
