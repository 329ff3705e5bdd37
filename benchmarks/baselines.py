"""The setting-aware baselines of a dataset: what a surrogate of the settings must beat.

    python benchmarks/baselines.py data/default --out benchmarks/results/baselines_default.json
    python benchmarks/baselines.py data/cfpa6 --test-split test --train-limit 24

Fits :func:`torch_ampn.baselines.setting_baselines` (the mean training trajectory, the nearest
training setting, a linear regression and POD + Gaussian process on the settings) on the
training split and rolls them out on the test split: rollout RMSE (mm, ply nodes, mean over
steps and trajectories) and the explained variance of the setting effect R^2 against the mean
trajectory. Prints a table; writes JSON atomically.
"""

from __future__ import annotations

import argparse
import datetime
import json
import time
from pathlib import Path

from torch_ampn.baselines import rollout_mse, setting_baselines, setting_effect_r2
from torch_ampn.data import TrajectoryDataset
from torch_ampn.rollout import rollout_rmse
from torch_ampn.utils.io import atomic_write_text


def evaluate(data_dir: Path, test_split: str = "test", train_limit: int | None = None) -> dict:
    """RMSE, MSE and R^2 of every setting-aware baseline on ``test_split`` of ``data_dir``."""
    train = list(TrajectoryDataset(data_dir, "train", max_cached_mb=0))[:train_limit]
    test = list(TrajectoryDataset(data_dir, test_split, max_cached_mb=0))
    out: dict = {"dataset": str(data_dir), "train": len(train), "test": len(test), "baselines": {}}
    for name, baseline in setting_baselines().items():
        start = time.perf_counter()
        baseline.fit(train)
        fit_seconds = time.perf_counter() - start
        preds = [baseline.predict(t) for t in test]
        pairs = list(zip(preds, test, strict=True))
        rmse = [float(rollout_rmse(p, t.pos, t.ply_mask)[1:].mean()) for p, t in pairs]
        mse = [rollout_mse(p, t.pos, t.ply_mask) for p, t in pairs]
        out["baselines"][name] = {
            "rmse": sum(rmse) / len(rmse),
            "rmse_per_trajectory": rmse,
            "mse": sum(mse) / len(mse),
            "fit_seconds": fit_seconds,
            "repr": repr(baseline),
        }
    reference = out["baselines"]["mean_trajectory"]["mse"]
    for row in out["baselines"].values():
        row["r2"] = setting_effect_r2(row["mse"], reference)
    out["date"] = datetime.date.today().isoformat()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--test-split", default="test")
    parser.add_argument("--train-limit", type=int, default=None, help="the first N training trajectories")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    result = evaluate(args.data_dir, args.test_split, args.train_limit)
    print(f"{args.data_dir}: {result['train']} training, {result['test']} {args.test_split} trajectories")
    print("| baseline | RMSE [mm] | R² of the setting effect |\n|---|---:|---:|")
    for name, row in result["baselines"].items():
        print(f"| {name} | {row['rmse']:.3f} | {row['r2']:.2f} |")
    if args.out:
        atomic_write_text(args.out, json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
