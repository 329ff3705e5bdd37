"""Where on the formed part a direct model errs, beside POD + GP: per ply, per ring, per axis.

    python benchmarks/direct_where.py data/v3_400 --train 192 \
        --checkpoint outputs/direct_runs/direct_ampn_v3_400_n192_s0_t2000/checkpoints/best.ckpt \
        --out benchmarks/results/direct/where_n192.json

The RMSE of the last saved step (the formed part) over the test split, as ``torch-ampn test``
computes it (root of the mean over trajectories, nodes and the 3 coordinates), of the direct
model and of POD + GP fitted on the same first ``--train`` training trajectories, over ply
nodes grouped by ply, by ring (the in-plane distance from the ply's centre, the Chebyshev
norm, so that the rings follow the square ply's edge) and by axis; and the share of the
squared error in the worst 10 % of nodes. A gap spread evenly over the part points at the
settings' effect as a whole; one in a ring or ply points at a local feature. Prints a table and
writes JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
from pathlib import Path

import torch

from torch_ampn.baselines import fitted_prior
from torch_ampn.data import TrajectoryDataset
from torch_ampn.rollout.direct import predict_direct
from torch_ampn.training import AMPNDataModule, load_module
from torch_ampn.utils.io import atomic_write_text

RINGS = ((0.0, 25.0), (25.0, 50.0), (50.0, 65.0), (65.0, float("inf")))  # mm from the ply's centre


def rmse(squared: torch.Tensor, select: torch.Tensor | None = None) -> float:
    """Root of the mean of ``squared [K, P, 3]`` over trajectories, the ``select``-ed nodes and axes."""
    return float((squared if select is None else squared[:, select]).mean().sqrt())


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument(
        "--train", type=int, required=True, help="training trajectories the model was fitted on"
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/direct/where.json"))
    args = parser.parse_args()
    train_set = TrajectoryDataset(args.data_dir, "train", max_cached_mb=0)
    if not 1 <= args.train <= len(train_set):
        raise ValueError(f"--train {args.train}: the dataset has {len(train_set)} training trajectories")
    test = list(TrajectoryDataset(args.data_dir, "test", max_cached_mb=0))
    module = load_module(args.checkpoint, map_location="cpu").eval()
    dm = AMPNDataModule(str(args.data_dir), generate=False, max_levels=module.hparams.num_levels)
    pod_gp = fitted_prior("pod_gp", [train_set[i] for i in range(args.train)])
    ply = test[0].ply_mask
    truth = torch.stack([t.pos[-1, ply].double() for t in test])  # [K, P, 3]
    inputs = test
    if module.surrogate.prior_features:  # base: prior; its prior is POD + GP on the same trajectories
        saved = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
        name = saved.get("datamodule_hyper_parameters", {}).get("prior")
        if name != "pod_gp":
            raise ValueError(f"{args.checkpoint}: the model reads the prior {name!r}; this script has pod_gp")
        inputs = [dataclasses.replace(t, prior=pod_gp.predict(t)) for t in test]
    direct = predict_direct(module.surrogate, inputs, dm.hierarchies(test[0]))
    predicted = {
        "direct": torch.stack([p[-1, ply].double() for p in direct]),
        "pod_gp": torch.stack([pod_gp.predict(t)[-1, ply].double() for t in test]),
    }
    squared = {name: (p - truth).square() for name, p in predicted.items()}  # [K, P, 3]
    x0 = test[0].pos[0, ply].double()  # [P, 3]
    component = test[0].component[ply]  # [P]
    groups: dict[str, torch.Tensor] = {"all": torch.ones(len(x0), dtype=torch.bool)}
    for c in component.unique().tolist():
        groups[f"ply {test[0].names[c]}"] = component == c
    for c in component.unique().tolist():
        mine = component == c
        centre = x0[mine, :2].mean(0)
        ring = (x0[:, :2] - centre).abs().amax(-1)
        for lo, hi in RINGS:
            key = f"ring {lo:g}-{hi:g} mm"
            groups[key] = groups.get(key, torch.zeros_like(mine)) | (mine & (ring >= lo) & (ring < hi))
    rows = []
    for key, select in groups.items():
        row = {"group": key, "nodes": int(select.sum())}
        row.update({f"{name}_rmse_mm": rmse(sq, select) for name, sq in squared.items()})
        rows.append(row)
    for axis, name in enumerate("xyz"):
        row = {"group": f"axis {name}", "nodes": len(x0)}
        row.update({f"{n}_rmse_mm": float(sq[..., axis].mean().sqrt()) for n, sq in squared.items()})
        rows.append(row)
    worst = {}
    for name, sq in squared.items():
        per_node = sq.sum((0, 2))  # [P]
        k = max(len(per_node) // 10, 1)
        worst[name] = float(per_node.sort(descending=True).values[:k].sum() / per_node.sum())
    print(f"{'group':<22} {'nodes':>6} {'direct':>8} {'POD + GP':>9} {'ratio':>6}  (mm, last step)")
    for r in rows:
        ratio = r["direct_rmse_mm"] / r["pod_gp_rmse_mm"]
        errors = f"{r['direct_rmse_mm']:>8.3f} {r['pod_gp_rmse_mm']:>9.3f} {ratio:>6.2f}"
        print(f"{r['group']:<22} {r['nodes']:>6} {errors}")
    print(f"share of the squared error in the worst 10 % of nodes: {worst}")
    result = {
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/direct_where.py " + " ".join(os.sys.argv[1:]),
        "checkpoint": args.checkpoint,
        "train": args.train,
        "test": len(test),
        "rows": rows,
        "worst_tenth_share": worst,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
