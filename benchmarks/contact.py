"""Contact-edge benchmark: component-kNN edges vs plain radius edges on the laminate mesh.

Builds the flat stand-in of the paper's mesh (``laminate_mesh(scale=s)``: four plies 0.5 mm
apart between a punch and a die, about 16k / 64k / 256k nodes for s = 1 / 2 / 4), and reports
for radius ``r`` and ``k`` neighbours per other component:

* the number of contact edges (component kNN) and of plain radius edges, and their ratio,
* the time per call (median of ``--repeats`` after ``--warmup`` calls; CUDA synchronised) of
  the pure-PyTorch grid backend (edge list and fixed-shape table), of the C grid
  (``backend="native"``, CPU) and of the torch-cluster backend when it is installed; the
  other backends' tables are checked equal to the grid's.

Usage::

    python benchmarks/contact.py --device cpu --sizes 1,2,4 --out benchmarks/results/contact_cpu.json
    python benchmarks/contact.py --device cuda --out benchmarks/results/contact_cuda.json
    python benchmarks/contact.py --fixed-density --out benchmarks/results/contact_cpu_fixed_density.json

By default a larger scale refines the same laminate, so at a fixed radius every node has
about ``scale**2`` times more nodes in range; ``--fixed-density`` grows the laminate instead.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.data import laminate_mesh
from torch_ampn.transforms import (
    component_radius_graph,
    component_radius_table,
    native_available,
    plain_radius_graph,
    torch_cluster_available,
)

from device_info import device_name  # benchmarks/device_info.py, beside this script


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--sizes", default="1,2,4", help="comma-separated laminate_mesh scales (default 1,2,4)")
    p.add_argument("--r", type=float, default=3.0, help="contact radius in mm (default 3)")
    p.add_argument("--k", type=int, default=3, help="neighbours per other component (default 3)")
    p.add_argument("--repeats", type=int, default=10, help="timed calls per measurement (default 10)")
    p.add_argument("--warmup", type=int, default=2, help="untimed calls before timing (default 2)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    p.add_argument("--no-cluster", action="store_true", help="skip the torch-cluster backend")
    p.add_argument(
        "--fixed-density",
        action="store_true",
        help="grow the laminate with the scale (ply size 150 mm x scale) instead of refining it, "
        "so node spacing and neighbours per node stay those of scale 1",
    )
    p.add_argument(
        "--out", default=None, help="JSON output (default benchmarks/results/contact_<device>.json)"
    )
    return p.parse_args()


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_call(fn, device: torch.device, repeats: int, warmup: int) -> dict[str, float]:
    """Median, min and max wall time of ``fn()`` in milliseconds."""
    for _ in range(warmup):
        fn()
    sync(device)
    times = []
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        fn()
        sync(device)
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": statistics.median(times), "min_ms": min(times), "max_ms": max(times)}


def bench_scale(scale: int, args: argparse.Namespace, device: torch.device) -> dict:
    mesh = laminate_mesh(scale=scale, ply_size=150.0 * scale if args.fixed_density else 150.0)
    pos, comp = mesh.pos.to(device), mesh.component.to(device)
    n, c = mesh.num_nodes, mesh.num_components
    r, k = args.r, args.k
    row: dict = {"scale": scale, "num_nodes": n, "num_components": c, "r": r, "k": k}
    row["fixed_density"] = bool(args.fixed_density)

    nbr, mask = component_radius_table(pos, comp, r, k, num_components=c, backend="grid")
    row["table_shape"] = list(nbr.shape)
    row["knn_edges"] = int(mask.sum())
    sync(device)
    start = time.perf_counter()
    plain = plain_radius_graph(pos, r)
    sync(device)
    row["plain_time_ms"] = (time.perf_counter() - start) * 1e3
    row["plain_edges"] = int(plain.size(1))
    row["plain_cross_component_edges"] = int((comp[plain[0]] != comp[plain[1]]).sum())
    del plain
    row["edge_ratio"] = row["plain_edges"] / max(row["knn_edges"], 1)

    reps, warm = args.repeats, args.warmup
    row["grid_edge_list"] = time_call(
        lambda: component_radius_graph(pos, comp, r, k, num_components=c, backend="grid"), device, reps, warm
    )
    row["grid_table"] = time_call(
        lambda: component_radius_table(pos, comp, r, k, num_components=c, backend="grid"), device, reps, warm
    )
    if device.type == "cpu" and native_available():

        def native():
            return component_radius_table(pos, comp, r, k, num_components=c, backend="native")

        row["native_table"] = time_call(native, device, reps, warm)
        native = native()
        row["native_equal"] = torch.equal(nbr, native[0]) and torch.equal(mask, native[1])
    if not args.no_cluster and torch_cluster_available():
        try:
            row["cluster_table"] = time_call(
                lambda: component_radius_table(pos, comp, r, k, num_components=c, backend="torch_cluster"),
                device,
                max(1, reps // 2),
                1,
            )
            cluster = component_radius_table(pos, comp, r, k, num_components=c, backend="torch_cluster")
            row["cluster_equal"] = torch.equal(nbr, cluster[0]) and torch.equal(mask, cluster[1])
        except RuntimeError as err:  # e.g. a CPU-only torch-cluster build with --device cuda
            row["cluster_error"] = str(err).splitlines()[0]
    return row


def print_table(rows: list[dict]) -> None:
    head = (
        f"{'scale':>5} {'nodes':>8} {'kNN edges':>10} {'plain edges':>12} {'ratio':>6} "
        f"{'edges ms':>9} {'table ms':>9} {'us/node':>8} {'native ms':>9} {'cluster ms':>10} {'plain ms':>9}"
    )
    print(head)
    print("-" * len(head))
    for row in rows:
        cluster = row.get("cluster_table", {}).get("median_ms")
        native = row.get("native_table", {}).get("median_ms")
        per_node = 1e3 * row["grid_table"]["median_ms"] / row["num_nodes"]
        print(
            f"{row['scale']:>5} {row['num_nodes']:>8} {row['knn_edges']:>10} {row['plain_edges']:>12} "
            f"{row['edge_ratio']:>6.1f} {row['grid_edge_list']['median_ms']:>9.1f} "
            f"{row['grid_table']['median_ms']:>9.1f} {per_node:>8.2f} "
            f"{'-' if native is None else f'{native:.1f}':>9} "
            f"{'-' if cluster is None else f'{cluster:.1f}':>10} "
            f"{row['plain_time_ms']:>9.1f}"
        )


def main() -> None:
    args = parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda but CUDA is not available")
    device = torch.device(args.device)
    rows = []
    for scale in [int(s) for s in args.sizes.split(",")]:
        rows.append(bench_scale(scale, args, device))
        print(f"scale {scale} done: {rows[-1]['num_nodes']} nodes", flush=True)
    print_table(rows)
    meta = {
        "device": args.device,
        "device_name": device_name(device),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "torch_cluster": torch_cluster_available(),
        "native": native_available(),
        "timing": f"median of {args.repeats} calls after {args.warmup} warm-up calls",
    }
    out = Path(args.out or f"benchmarks/results/contact_{args.device}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
