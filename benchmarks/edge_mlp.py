"""Benchmark: an edge LayerNormMLP on concatenated inputs versus ``LayerNormMLP.forward_edges``.

Both compute ``f(cat([x_i, x_j, e_ij]))`` for every edge, the edge update of every AMPN
layer. The plain form gathers and concatenates ``[E, 3d]`` and multiplies it by ``W_1``;
``forward_edges`` multiplies the node blocks once per node and gathers ``[E, d + 2]`` rows.
Median time of forward + backward, side by side in one process; prints a table and writes JSON.

    python benchmarks/edge_mlp.py --device cpu
    python benchmarks/edge_mlp.py --device cuda
    python benchmarks/edge_mlp.py --training-step data/default   # + whole quickstart training steps

``--training-step DIR`` also times whole training steps of the quickstart model (batches of
4 cached windows from the dataset in ``DIR``, forward + backward + Adam) with the layers'
edge MLPs switched between the two forms, interleaved in one process.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.nn import LayerNormMLP

from device_info import device_name  # benchmarks/device_info.py, beside this script


def _time(fn, repeats: int, device: torch.device) -> float:
    """Median seconds of ``fn`` (forward + backward) after two warm-up calls."""
    for _ in range(2):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def run_case(num_nodes: int, num_edges: int, channels: int, repeats: int, device: torch.device) -> dict:
    """Time both forms on random features of one size; returns a result row."""
    g = torch.Generator().manual_seed(0)
    mlp = LayerNormMLP(3 * channels, channels, hidden_channels=channels).to(device)
    x = torch.randn(num_nodes, channels, generator=g).to(device).requires_grad_()
    e = torch.randn(num_edges, channels, generator=g).to(device).requires_grad_()
    edge_index = torch.randint(0, num_nodes, (2, num_edges), generator=g).to(device)

    def concatenated() -> None:
        mlp(torch.cat([x[edge_index[1]], x[edge_index[0]], e], dim=-1)).square().sum().backward()

    def split() -> None:
        mlp.forward_edges(x, x, e, edge_index).square().sum().backward()

    # Interleave the two so slow drifts of a shared machine hit both alike.
    t_cat, t_split = [], []
    for _ in range(3):
        t_cat.append(_time(concatenated, repeats, device))
        t_split.append(_time(split, repeats, device))
    cat_s, split_s = statistics.median(t_cat), statistics.median(t_split)
    return {
        "nodes": num_nodes,
        "edges": num_edges,
        "d": channels,
        "concatenated_s": cat_s,
        "forward_edges_s": split_s,
        "speedup": cat_s / split_s,
    }


def _concatenated_forward_edges(
    self: LayerNormMLP,
    x_dst: torch.Tensor,
    x_src: torch.Tensor,
    edge_attr: torch.Tensor,
    edge_index: torch.Tensor,
) -> torch.Tensor:
    """The plain form, with ``forward_edges``'s signature (to swap it in)."""
    return self(torch.cat([x_dst[edge_index[1]], x_src[edge_index[0]], edge_attr], dim=-1))


def run_training_steps(data_dir: str, rounds: int = 4, steps: int = 17) -> dict:
    """Median ms per quickstart training step with each edge-LayerNormMLP form, interleaved rounds."""
    from training_step import QuickstartCase  # benchmarks/training_step.py, next to this script

    case = QuickstartCase(data_dir, {}, steps + 3, compile_network=False)
    batches, step = case.batches, case.step

    forms = {"concatenated": _concatenated_forward_edges, "forward_edges": LayerNormMLP.forward_edges}
    times: dict[str, list[float]] = {name: [] for name in forms}
    try:
        for batch in batches[:3]:
            step(batch)
        for r in range(rounds):
            for name in list(forms) if r % 2 == 0 else list(forms)[::-1]:
                LayerNormMLP.forward_edges = forms[name]
                start = time.perf_counter()
                for batch in batches[3:]:
                    step(batch)
                times[name].append((time.perf_counter() - start) / steps)
    finally:
        LayerNormMLP.forward_edges = forms["forward_edges"]
    cat_s, split_s = statistics.median(times["concatenated"]), statistics.median(times["forward_edges"])
    return {"concatenated_s": cat_s, "forward_edges_s": split_s, "speedup": cat_s / split_s, "rounds": times}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--training-step", metavar="DATA_DIR", default=None)
    args = parser.parse_args()
    device = torch.device(args.device)
    cases = [(9_000, 70_000, 32), (9_000, 70_000, 128), (16_390, 122_004, 128)]
    rows = [run_case(n, e, d, args.repeats, device) for n, e, d in cases]
    print(f"{'nodes':>7} {'edges':>8} {'d':>4} {'cat [ms]':>9} {'split [ms]':>10} {'speed-up':>8}")
    for r in rows:
        print(
            f"{r['nodes']:>7} {r['edges']:>8} {r['d']:>4} {1e3 * r['concatenated_s']:>9.1f} "
            f"{1e3 * r['forward_edges_s']:>10.1f} {r['speedup']:>7.2f}x"
        )
    result = {"rows": rows}
    if args.training_step is not None:
        result["training_step"] = run_training_steps(args.training_step)
        t = result["training_step"]
        print(
            f"quickstart training step (batch of 4): concatenated {1e3 * t['concatenated_s']:.0f} ms, "
            f"forward_edges {1e3 * t['forward_edges_s']:.0f} ms, {t['speedup']:.2f}x"
        )
    out = args.out or Path(__file__).parent / "results" / f"edge_mlp_{device.type}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "torch": torch.__version__, "threads": torch.get_num_threads()}
    meta["machine"] = device_name(device)
    out.write_text(json.dumps({"meta": meta, **result}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
