"""Benchmark: AMG hierarchy of the paper-sized laminate mesh and of 4x / 16x larger ones.

Prints nodes and edges per level and the build time (median of repeats, CPU: pyamg and
scipy run on the CPU), and writes JSON.

    python benchmarks/hierarchy.py --out benchmarks/results/hierarchy.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.data import build_hierarchy, laminate_mesh

from device_info import device_name  # benchmarks/device_info.py, beside this script


def measure(scale: int, max_levels: int, repeats: int, operator: str) -> dict:
    mesh = laminate_mesh(scale=scale)
    edge_index = mesh.edge_index()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        h = build_hierarchy(edge_index, mesh.num_nodes, max_levels=max_levels, operator=operator)
        times.append(time.perf_counter() - t0)
    levels = []
    for k in range(h.num_levels):
        levels.append(
            dict(
                level=k,
                nodes=int(h.level(k).num_nodes),
                mesh_edges=int(h.mesh(k).edge_index.size(1)),
                down_edges=int(h.down(k).edge_index.size(1)) if k < h.num_levels - 1 else 0,
            )
        )
    return dict(
        scale=scale,
        nodes=mesh.num_nodes,
        cells=sum(int(c.size(0)) for c in mesh.cells),
        operator=operator,
        max_levels=max_levels,
        num_levels=h.num_levels,
        build_seconds_median=statistics.median(times),
        build_seconds_all=times,
        levels=levels,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scales", type=int, nargs="+", default=[1, 2, 4], help="1: paper mesh; 2: 4x; 4: 16x"
    )
    parser.add_argument("--max-levels", type=int, nargs="+", default=[4, 10])
    parser.add_argument("--operator", default="adjacency", choices=["adjacency", "laplacian"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/hierarchy.json"))
    args = parser.parse_args()

    torch.set_num_threads(torch.get_num_threads())
    results = [measure(s, m, args.repeats, args.operator) for s in args.scales for m in args.max_levels]

    header = (
        f"{'mesh':>6} {'nodes':>8} {'max_lv':>6} {'levels':>6} {'build [s]':>9}  nodes per level (mesh edges)"
    )
    print(header)
    print("-" * len(header))
    for r in results:
        per_level = ", ".join(f"{lv['nodes']} ({lv['mesh_edges']})" for lv in r["levels"])
        name = f"{r['scale'] ** 2}x"
        print(
            f"{name:>6} {r['nodes']:>8} {r['max_levels']:>6} {r['num_levels']:>6} "
            f"{r['build_seconds_median']:>9.3f}  {per_level}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(
        benchmark="hierarchy",
        machine=platform.machine(),
        processor=device_name("cpu"),
        cpu_count=torch.get_num_threads(),
        torch=torch.__version__,
    )
    args.out.write_text(json.dumps(dict(meta=meta, results=results), indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
