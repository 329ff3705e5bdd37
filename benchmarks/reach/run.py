"""The reach benchmark: where does an AMG hierarchy pay? Trains and tests networks on steady problems.

Every cell (problem, mesh size, network, seed) trains one network for the same wall-clock
budget on the dataset of :mod:`reach_data` and writes its result to
``benchmarks/results/reach/cells/PROBLEM_SIZE_NETWORK_sSEED.json`` (atomically); cells whose
file exists are skipped, so an interrupted grid resumes. ``report.py`` makes the table and figure.

    python benchmarks/reach/run.py --problems laplace elasticity smoothing \\
        --sizes 50000 16000 4000 1000 --budget 300 180 120 60 \\
        --networks ampn flat flat_deep graph_unet --seeds 0 1 2

Training: Adam, learning rate ``--lr`` with a 5 % linear warm-up and a cosine decay over the
time budget (the schedule follows the elapsed time, so every network ends its decay at the
budget), one batch of about 4k nodes per step (one mesh from 4k nodes on), MSE of the target
divided by its training RMS on the nodes the error is measured on. The error: the relative L2
error ``||u_pred - u|| / ||u||`` over those nodes of every test mesh, averaged over the test
meshes, and per bin of hop distance from the data the answer depends on.

Levers of the training (each recorded in the cell, and named by ``--tag``): ``--normalize``
gives every AMPN-built network (the AMPNs and both flat ones) online input normalisation
(``AMPN(normalize=True)``; GraphUNet always standardises its inputs); ``--augment`` multiplies
the data channels of every training sample (``PROBLEMS[problem]["data_channels"]``) and its
target by one random ``a ~ N(0, 1)`` per sample and step. Every problem is linear in its data,
so the scaled sample is an exact sample of the same problem: a network then sees every
amplitude and sign of the data instead of the training set's few.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch_geometric.data import Batch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from networks import UNet, build, count, layer_calls  # noqa: E402
from reach_data import describe, load  # noqa: E402  (benchmarks/reach/, beside this script)

from torch_ampn.datasets import PROBLEMS  # noqa: E402

RESULTS = Path("benchmarks/results/reach")
#: Hop-distance bins: [0, 2], [3, 5], [6, 11], [12, 23], [24, 47], [48, 95], [96, ...)
HOP_EDGES = [0, 3, 6, 12, 24, 48, 96]
NODES_PER_BATCH = 4_000


def hop_bin(hop: torch.Tensor) -> torch.Tensor:
    """Bin index of every hop distance ``[N] -> [N]``."""
    return torch.bucketize(hop, torch.tensor(HOP_EDGES[1:]), right=True)


def learning_rate(lr: float, fraction: float) -> float:
    """5 % linear warm-up, then a cosine decay to 0 at ``fraction = 1``."""
    if fraction < 0.05:
        return lr * max(fraction / 0.05, 0.02)
    return lr * 0.5 * (1 + math.cos(math.pi * min((fraction - 0.05) / 0.95, 1.0)))


def train(
    model: torch.nn.Module,
    samples: list,
    scale: torch.Tensor,
    budget: float,
    lr: float,
    seed: int,
    augment: list[int] | None = None,
) -> dict:
    """Train for ``budget`` seconds; returns steps and seconds.

    ``augment``: the data channels to scale, with the target, by ``a ~ N(0, 1)`` per sample.
    """
    generator = torch.Generator().manual_seed(seed)
    per_batch = max(1, NODES_PER_BATCH // samples[0]["l0"].num_nodes)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    model.train()
    start, steps, losses = time.perf_counter(), 0, []
    with tqdm(total=round(budget), desc="train", unit="s", leave=False, mininterval=5) as bar:
        while (elapsed := time.perf_counter() - start) < budget:
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(lr, elapsed / budget)
            pick = torch.randperm(len(samples), generator=generator)[:per_batch].tolist()
            batch = Batch.from_data_list([samples[i] for i in pick]) if per_batch > 1 else samples[pick[0]]
            mask, x, y = batch["l0"].mask, batch["l0"].x, batch["l0"].y  # x [N, F], y [N, C]
            if augment:
                a = torch.randn(per_batch, generator=generator)  # [B]: one factor per sample
                a = a[batch["l0"].batch][:, None] if per_batch > 1 else a[:, None]  # [N, 1] or [1, 1]
                scaled = x.clone()
                scaled[:, augment] = x[:, augment] * a
                batch["l0"].x = scaled
                y = y * a
            loss = (model(batch)[mask] - y[mask] / scale).square().mean()
            batch["l0"].x = x  # the stored sample stays as it was
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            steps += 1
            losses.append(float(loss.detach()))
            bar.set_postfix(loss=f"{sum(losses[-20:]) / len(losses[-20:]):.3g}", steps=steps, refresh=False)
            bar.update(round(min(time.perf_counter() - start, budget)) - bar.n)  # seconds so far
    seconds = time.perf_counter() - start
    return {
        "steps": steps,
        "train_seconds": seconds,
        "seconds_per_step": seconds / steps,
        "final_loss": losses[-1],
    }


@torch.no_grad()
def evaluate(model: torch.nn.Module, samples: list, scale: torch.Tensor) -> dict:
    """Relative L2 error per test mesh and per hop bin, and seconds per prediction."""
    model.eval()
    errors, times = [], []
    bins = len(HOP_EDGES)
    err_sq, ref_sq, nodes = (
        torch.zeros(bins, dtype=torch.float64),
        torch.zeros(bins, dtype=torch.float64),
        torch.zeros(bins),
    )
    for h in samples:
        start = time.perf_counter()
        pred = model(h) * scale  # [N, C]
        times.append(time.perf_counter() - start)
        mask = h["l0"].mask
        e = (pred - h["l0"].y)[mask].double().square().sum(-1)  # [M]
        r = h["l0"].y[mask].double().square().sum(-1)
        errors.append(float(e.sum().sqrt() / r.sum().sqrt()))
        b = hop_bin(h["l0"].hop[mask])
        err_sq.index_add_(0, b, e)
        ref_sq.index_add_(0, b, r)
        nodes.index_add_(0, b, torch.ones_like(b, dtype=torch.float))
    by_hop = [
        {"hops_from": HOP_EDGES[i], "nodes": int(nodes[i]), "rel_l2": float((err_sq[i] / ref_sq[i]).sqrt())}
        for i in range(bins)
        if nodes[i] > 0
    ]
    return {
        "rel_l2": sum(errors) / len(errors),
        "rel_l2_per_mesh": errors,
        "by_hop": by_hop,
        "seconds_per_prediction": sorted(times)[len(times) // 2],
    }


def run_cell(problem: str, size: int, network: str, seed: int, args: argparse.Namespace) -> dict:
    """Train and test one network; the cell's record."""
    data = load(problem, size)
    spec = PROBLEMS[problem]
    train_set, test_set, levels = data["train"], data["test"], data["levels"]
    levels = min(levels, args.max_levels)
    torch.manual_seed(seed)
    edge_channels = train_set[0]["l0", "mesh", "l0"].edge_attr.size(1)
    common = {"normalize": True} if args.normalize else {}
    model = build(
        network, spec["in_channels"], spec["out_channels"], edge_channels, levels, args.width, common
    )
    if isinstance(model, UNet):
        model.fit_inputs([h["l0"].x for h in train_set])
    y = torch.cat([h["l0"].y[h["l0"].mask] for h in train_set])
    scale = y.square().mean(0).sqrt()  # [C]: the target's RMS per channel
    augment = spec["data_channels"] if args.augment else None
    fit = train(model, train_set, scale, args.budget_seconds, args.lr, seed, augment)
    result = evaluate(model, test_set, scale)
    return {
        "problem": problem,
        "size": size,
        "nodes": test_set[0]["l0"].num_nodes,
        "levels": levels,
        "hierarchy": describe(test_set[0]),
        "network": network,
        "seed": seed,
        "parameters": count(model),
        "options": (model.model if hasattr(model, "model") else model).extra_repr(),
        "layer_calls": layer_calls(levels) if network.startswith("ampn") else None,
        "budget_seconds": args.budget_seconds,
        "lr": args.lr,
        "width": args.width,
        "tag": args.tag,
        "normalize": args.normalize,
        "augment": args.augment,
        "train_meshes": len(train_set),
        "test_meshes": len(test_set),
        "torch_threads": torch.get_num_threads(),
        "date": time.strftime("%Y-%m-%d"),
        **fit,
        **result,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--problems", nargs="+", default=["laplace", "elasticity", "smoothing"], choices=PROBLEMS
    )
    parser.add_argument("--sizes", nargs="+", type=int, default=[1000, 4000, 16000, 50000])
    parser.add_argument("--networks", nargs="+", default=["ampn", "flat", "flat_deep", "graph_unet"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument(
        "--budget",
        type=float,
        nargs="+",
        default=[300.0],
        help="training seconds per network: one, or one per size",
    )
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument(
        "--width", type=int, default=32, help="the AMPN's d (the others match its parameters)"
    )
    parser.add_argument("--max-levels", type=int, default=6)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (two cells can run side by side)"
    )
    parser.add_argument(
        "--normalize", action="store_true", help="online input normalisation in every AMPN-built network"
    )
    parser.add_argument(
        "--augment", action="store_true", help="scale each sample's data and target by a ~ N(0, 1)"
    )
    parser.add_argument("--tag", default="", help="appended to the cell names (a lever study's own cells)")
    parser.add_argument("--out", type=Path, default=RESULTS / "cells")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    if len(args.budget) not in (1, len(args.sizes)):
        parser.error(f"--budget: one value or one per size ({len(args.sizes)}), got {len(args.budget)}")
    per_size = args.budget * len(args.sizes) if len(args.budget) == 1 else args.budget
    budgets = dict(zip(args.sizes, per_size, strict=True))
    for problem in args.problems:
        for size in args.sizes:
            args.budget_seconds = budgets[size]
            for seed in args.seeds:
                for network in args.networks:
                    path = args.out / f"{problem}_{size}_{network}{args.tag}_s{seed}.json"
                    if path.exists():
                        continue
                    record = run_cell(problem, size, network, seed, args)
                    tmp = path.with_suffix(".tmp")
                    tmp.write_text(json.dumps(record, indent=1))
                    tmp.replace(path)
                    print(
                        f"{problem:10s} {record['nodes']:6d} nodes  {network:16s} seed {seed}: "
                        f"rel L2 {record['rel_l2']:.4f}  ({record['steps']} steps, "
                        f"{record['seconds_per_step']:.3f} s/step, {record['parameters']:,} parameters)",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
