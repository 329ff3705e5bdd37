"""Benchmark: seconds per trajectory of the embedded simulator, coarse and paper resolution.

    python benchmarks/simulate.py --out benchmarks/results/simulate_cpu.json

For each resolution, simulates ``--batch`` trajectories at once, eager and compiled, and
prints seconds per trajectory. Compiled runs are done twice: the first includes
``torch.compile``'s work, the second finds inductor's on-disk cache warm (what a dataset
generation with many batches sees).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

from torch_ampn.sim import StampFormingConfig, simulate_batch


def timed(cfg: StampFormingConfig, batch: int, compile_: bool) -> tuple[float, int, int]:
    t0 = time.perf_counter()
    trajs = simulate_batch(cfg, list(range(batch)), compile=compile_)
    return time.perf_counter() - t0, trajs[0].num_nodes, trajs[0].meta["substeps"]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--resolutions", nargs="+", default=["coarse", "paper"])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--modes", nargs="+", default=["eager", "compiled"])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/simulate_cpu.json"))
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    rows = []
    meta = dict(
        benchmark="simulate",
        machine=platform.machine(),
        threads=torch.get_num_threads(),
        torch=torch.__version__,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for res in args.resolutions:
        cfg = StampFormingConfig.paper() if res == "paper" else StampFormingConfig()
        for batch in args.batch:
            for mode in args.modes:
                compile_ = mode == "compiled"
                first = None
                if compile_:
                    first, _, _ = timed(cfg, batch, True)
                seconds, nodes, substeps = timed(cfg, batch, compile_)
                row = dict(
                    resolution=res,
                    nodes=nodes,
                    batch=batch,
                    mode=mode,
                    substeps_per_step=substeps,
                    seconds_total=seconds,
                    seconds_per_trajectory=seconds / batch,
                    first_run_seconds_per_trajectory=None if first is None else first / batch,
                )
                rows.append(row)
                args.out.write_text(json.dumps(dict(meta=meta, results=rows), indent=2))  # after every row
                print(
                    f"{res:>6} {nodes:>6} nodes  batch {batch}  {mode:>8}: {seconds / batch:7.2f} s/traj."
                    f"  ({substeps} sub-steps per saved step"
                    f"{f'; first run {first / batch:.2f} s/trajectory' if compile_ else ''})",
                    flush=True,
                )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(
        benchmark="simulate",
        machine=platform.machine(),
        threads=torch.get_num_threads(),
        torch=torch.__version__,
    )
    args.out.write_text(json.dumps(dict(meta=meta, results=rows), indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
