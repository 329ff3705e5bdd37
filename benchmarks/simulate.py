"""Benchmark: seconds per trajectory of the embedded simulator at the coarse, the paper or any resolution.

    python benchmarks/simulate.py --out benchmarks/results/simulate_cpu.json
    python benchmarks/simulate.py --physics v2 v3 --resolutions coarse --batch 4 --modes compiled \\
        --out benchmarks/results/simulate_v2_v3.json                      # data versions side by side
    python benchmarks/simulate.py --device cuda --resolutions paper --batch 8 32 --modes compiled \\
        --out benchmarks/results/simulate_cuda.json                        # on a GPU
    python benchmarks/simulate.py --resolutions coarse cells=24 --batch 4 --modes compiled \\
        --out benchmarks/results/simulate_c24.json                         # a mesh 1.5 times finer

A resolution is ``coarse``, ``paper`` or ``cells=N``: the coarse config with ``N`` cells per
ply edge and the tool meshes' cells scaled by the same factor (``cells=24`` is the mesh of
``torch-ampn-data generate --simulator
'{"ply_cells": 24, "punch_cells": [21, 21], "die_cells": [24, 24]}'``). For each resolution,
simulates ``--batch`` trajectories at once, eager and compiled, and
prints seconds per trajectory. Compiled runs are done twice: the first includes
``torch.compile``'s work, the second finds inductor's on-disk cache warm (what a dataset
generation with many batches sees). The cost of a trajectory is its number of explicit
sub-steps (process duration over the stable time step), whatever the number of saved steps.
Writes JSON atomically after every row.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import torch

from torch_ampn.sim import StampFormingConfig, simulate_batch
from torch_ampn.sim.config import PHYSICS_V2

from device_info import device_name  # benchmarks/device_info.py, beside this script


def timed(
    cfg: StampFormingConfig, batch: int, compile_: bool, device: str, seed: int = 0
) -> tuple[float, int, int]:
    t0 = time.perf_counter()
    # CPU results: synced
    trajs = simulate_batch(cfg, list(range(seed, seed + batch)), compile=compile_, device=device)
    return time.perf_counter() - t0, trajs[0].num_nodes, trajs[0].meta["substeps"]


def resolution_config(name: str, overrides: dict) -> StampFormingConfig:
    """The simulator config of ``coarse``, ``paper`` or ``cells=N`` (see the module docstring)."""
    if name == "paper":
        return StampFormingConfig.paper(**overrides)
    if name == "coarse":
        return StampFormingConfig(**overrides)
    key, _, value = name.partition("=")
    if key != "cells" or not value.isdigit() or int(value) < 2:
        raise SystemExit(f"--resolutions: {name!r} is not coarse, paper or cells=N (N >= 2)")
    coarse, n = StampFormingConfig(), int(value)

    def scaled(cells: tuple[int, int]) -> tuple[int, int]:
        return tuple(round(c * n / coarse.ply_cells) for c in cells)  # type: ignore[return-value]

    return StampFormingConfig(
        ply_cells=n, punch_cells=scaled(coarse.punch_cells), die_cells=scaled(coarse.die_cells), **overrides
    )


def write_json(path: Path, payload: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, path)


def main() -> None:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("--resolutions", nargs="+", default=["coarse", "paper"])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--modes", nargs="+", default=["eager", "compiled"])
    parser.add_argument("--device", default="cpu", help="where the solver runs (cpu, cuda)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="the first setting's seed (then seed + 1, ...)")
    parser.add_argument(
        "--physics", nargs="+", default=["v3"], choices=["v2", "v3"],
        help="the simulator's physics: data version 3 (the default) or 2 (PHYSICS_V2)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/simulate_cpu.json"))
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    meta = dict(
        benchmark="simulate",
        date=time.strftime("%Y-%m-%d"),
        machine=platform.machine(),
        device=device_name(args.device),
        threads=torch.get_num_threads(),
        seed=args.seed,
        torch=torch.__version__,
    )
    rows = []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for res, physics in ((r, p) for r in args.resolutions for p in args.physics):
        overrides = PHYSICS_V2 if physics == "v2" else {}
        cfg = resolution_config(res, overrides)
        for batch in args.batch:
            for mode in args.modes:
                compile_ = mode == "compiled"
                try:
                    first = timed(cfg, batch, True, args.device, args.seed)[0] if compile_ else None
                    seconds, nodes, substeps = timed(cfg, batch, compile_, args.device, args.seed)
                except FloatingPointError as err:  # a run that blows up is a result, too
                    failed = dict(resolution=res, physics=physics, batch=batch, mode=mode, diverged=str(err))
                    rows.append(failed)
                    write_json(args.out, dict(meta=meta, results=rows))
                    print(f"{res:>6} {physics} batch {batch:>3} {mode:>8}: {err}", flush=True)
                    continue
                per_traj = seconds / batch
                rows.append(
                    dict(
                        resolution=res,
                        physics=physics,
                        nodes=nodes,
                        batch=batch,
                        mode=mode,
                        device=args.device,
                        substeps_per_step=substeps,
                        seconds_total=seconds,
                        seconds_per_trajectory=per_traj,
                        first_run_seconds_per_trajectory=None if first is None else first / batch,
                    )
                )
                write_json(args.out, dict(meta=meta, results=rows))
                print(
                    f"{res:>6} {physics} {nodes:>6} nodes  batch {batch:>3}  {mode:>8} on {args.device}: "
                    f"{per_traj:7.2f} s/trajectory"
                    f"  ({substeps} sub-steps per saved step"
                    f"{f'; first run {first / batch:.2f} s/trajectory' if compile_ else ''})",
                    flush=True,
                )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
