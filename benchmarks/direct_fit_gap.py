"""Underfitted or overfitted? A direct model's RMSE on its own training trajectories and on the test split.

    python benchmarks/direct_fit_gap.py data/v3_400 \
        --run 400 outputs/direct_runs/direct_ampn_v3_400_n400_s0/checkpoints/best.ckpt \
        --run 192 outputs/direct_runs/direct_ampn_v3_400_n192_s0/checkpoints/best.ckpt \
        --out benchmarks/results/direct/fit_gap.json

Each ``--run N CKPT`` is a direct model fitted on the first ``N`` training trajectories of the
dataset (as ``benchmarks/direct.py`` fits them). Scored as ``torch-ampn test`` scores (rollout
RMSE over ply nodes, mean over the saved steps) on ``--sample`` of those ``N`` training
trajectories (evenly spaced) and on the whole test split, beside POD + GP fitted on the same
``N``. A model whose training error is as large as its test error is limited by its fit, not by
the data. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
from pathlib import Path
from typing import Any

import torch

from torch_ampn.baselines import fitted_prior
from torch_ampn.data import Trajectory, TrajectoryDataset
from torch_ampn.rollout import rollout_rmse
from torch_ampn.rollout.direct import predict_direct
from torch_ampn.training import AMPNDataModule, load_module
from torch_ampn.utils.io import atomic_write_text


def mean_rmse(predictions: list[torch.Tensor], trajs: list[Trajectory]) -> float:
    """Mean over trajectories of the rollout RMSE over ply nodes and saved steps 1..T (mm)."""
    return statistics.fmean(
        float(rollout_rmse(p, t.pos, t.ply_mask)[1:].mean()) for p, t in zip(predictions, trajs, strict=True)
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--run", nargs=2, action="append", metavar=("N", "CKPT"), required=True)
    parser.add_argument("--sample", type=int, default=32, help="training trajectories scored per run")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/direct/fit_gap.json"))
    args = parser.parse_args()
    train_set = TrajectoryDataset(args.data_dir, "train", max_cached_mb=0)
    test = list(TrajectoryDataset(args.data_dir, "test", max_cached_mb=0))
    rows = []
    pod_gp_of: dict[int, Any] = {}  # training-set size -> POD + GP fitted on it (runs may share one)
    for n_text, ckpt in args.run:
        n = int(n_text)
        if not 1 <= n <= len(train_set):
            raise ValueError(f"--run {n_text}: the dataset has {len(train_set)} training trajectories")
        module = load_module(ckpt, map_location="cpu").eval()
        dm = AMPNDataModule(str(args.data_dir), generate=False, max_levels=module.hparams.num_levels)
        hierarchy = dm.hierarchies(test[0])
        train = [train_set[i] for i in range(n)]
        seen = train[:: max(n // args.sample, 1)][: args.sample]
        if n not in pod_gp_of:
            pod_gp_of[n] = fitted_prior("pod_gp", train)
        pod_gp = pod_gp_of[n]
        row = {"train": n, "checkpoint": ckpt, "sample": len(seen), "test": len(test)}
        for split, trajs in (("train", seen), ("test", test)):
            predicted = predict_direct(module.surrogate, trajs, hierarchy)
            row[f"direct_{split}_rmse_mm"] = mean_rmse(predicted, trajs)
            row[f"pod_gp_{split}_rmse_mm"] = mean_rmse([pod_gp.predict(t) for t in trajs], trajs)
        rows.append(row)
        d = f"direct train {row['direct_train_rmse_mm']:.3f} test {row['direct_test_rmse_mm']:.3f} mm"
        g = f"POD + GP train {row['pod_gp_train_rmse_mm']:.3f} test {row['pod_gp_test_rmse_mm']:.3f} mm"
        print(f"n={n}: {d}; {g}")
    result = {
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/direct_fit_gap.py " + " ".join(os.sys.argv[1:]),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(result, indent=2))


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()
    main()
