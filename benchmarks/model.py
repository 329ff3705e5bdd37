"""Benchmark: AMPN forward and forward+backward time per step on the paper-sized hierarchy.

The hierarchy is ``build_hierarchy(laminate_mesh(scale).edge_index(), max_levels=4)``
(~16k nodes at ``scale=1``, 4 levels), with the paper's features and contact edges on every
level (``torch_ampn.transforms.component_radius_graph`` with r=3, k=3 when it is available,
otherwise a stand-in of random cross-component pairs, k per node and other component).
Variants: hierarchical (4 levels) and flat baseline (``num_levels=1``), fp32 and bf16
autocast, eager and ``torch.compile``. Reports median seconds per step, peak GPU memory on
CUDA, prints a table and writes JSON.

    python benchmarks/model.py --device cpu --repeats 1
    python benchmarks/model.py --device cuda --compile --repeats 10
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.data import NodeType, build_hierarchy, laminate_mesh, level_name
from torch_ampn.forming import Normalizer, ampn_channels, hierarchical_features
from torch_ampn.nn import RobinAMPN

from device_info import device_name  # benchmarks/device_info.py, beside this script

NUM_GRIPPERS = 2  # per quarter model


def random_contact_edges(component: torch.Tensor, k: int, generator: torch.Generator) -> torch.Tensor:
    """Stand-in contact edges: for every node and other component, k random nodes of that component."""
    n = component.numel()
    src, dst = [], []
    for c in component.unique().tolist():
        members = torch.nonzero(component == c).flatten()
        targets = torch.nonzero(component != c).flatten()
        pick = torch.randint(0, members.numel(), (targets.numel(), k), generator=generator)
        src.append(members[pick].flatten())
        dst.append(targets.repeat_interleave(k))
    ei = torch.stack([torch.cat(src), torch.cat(dst)])
    return ei[:, torch.argsort(ei[1] * n + ei[0])]


def make_data(scale: int, num_levels: int, k: int, seed: int = 0):
    """The benchmark hierarchy with all fields of one forming step, and how contact edges were made."""
    g = torch.Generator().manual_seed(seed)
    mesh = laminate_mesh(scale=scale)
    h = build_hierarchy(mesh.edge_index(), mesh.num_nodes, max_levels=num_levels)
    n = mesh.num_nodes
    tool = mesh.node_type != int(NodeType.PLY)
    fine = h["l0"]
    fine.pos0 = mesh.pos
    fine.pos = mesh.pos + 0.01 * torch.randn(n, 3, generator=g)
    fine.prev_disp = 0.01 * torch.randn(n, 3, generator=g)
    fine.bc_disp = torch.where(
        (mesh.node_type == int(NodeType.PUNCH))[:, None], torch.tensor([0.0, 0.0, -1.2]), torch.zeros(3)
    )
    angle = (mesh.component.float() * torch.pi / 4).unsqueeze(-1)
    fiber = torch.cat([angle.cos(), angle.sin(), torch.zeros_like(angle)], -1)
    fine.fiber = torch.where(tool[:, None], torch.zeros(3), fiber)
    fine.node_type = mesh.node_type
    fine.component = mesh.component
    h.gripper_pos = 150.0 * torch.rand(1, NUM_GRIPPERS, 3, generator=g)
    h.gripper_force = 100.0 * torch.rand(1, NUM_GRIPPERS, 3, generator=g)
    try:
        from torch_ampn.transforms import component_radius_graph

        source = "component_radius_graph(r=3, k=3)"
    except ImportError:
        component_radius_graph, source = None, f"random cross-component pairs (k={k})"
    for level in range(h.num_levels):
        idx = h.fine_index(level)
        lk = level_name(level)
        if component_radius_graph is not None:
            ei = component_radius_graph(fine.pos[idx], mesh.component[idx], r=3.0, k=k)
        else:
            ei = random_contact_edges(mesh.component[idx], k, g)
        h[lk, "contact", lk].edge_index = ei
    return h, mesh.num_components, source


def normalized_features(h, num_components: int):
    """Features normalised with statistics of this sample (as a fitted Normalizer would)."""
    x_dict, e_dict = hierarchical_features(h, num_components)
    out_x, out_e = {}, {}
    for key, x in x_dict.items():
        norm = Normalizer(x.size(-1))
        norm.update(x)
        out_x[key] = norm.freeze()(x)
    for key, e in e_dict.items():
        norm = Normalizer(e.size(-1))
        norm.update(e)
        out_e[key] = norm.freeze()(e)
    return out_x, out_e


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_steps(step, repeats: int, warmup: int, device: torch.device) -> list[float]:
    for _ in range(warmup):
        step()
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        sync(device)
        times.append(time.perf_counter() - t0)
    return times


def run_variant(args, data, device, num_levels: int, dtype: str, compiled: bool) -> dict:
    h, x_dict, e_dict, ei_dict, sizes = data
    torch.manual_seed(0)
    width = dict(hidden_channels=args.hidden, mlp_channels=args.hidden)
    model = RobinAMPN(**sizes, **width, num_levels=num_levels, noise_channels=3).to(device)
    fn = torch.compile(model) if compiled else model
    noise = torch.randn(x_dict["l0"].size(0), 3, device=device)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=dtype == "bf16")

    def forward():
        with torch.no_grad(), autocast:
            return fn(x_dict, ei_dict, e_dict, noise=noise)

    def train_step():
        with autocast:
            loss = fn(x_dict, ei_dict, e_dict, noise=noise).float().square().mean()
        loss.backward()
        model.zero_grad(set_to_none=True)

    warmup = args.warmup + (1 if compiled else 0)
    result = dict(
        model="hierarchical" if num_levels > 1 else "flat",
        num_levels=num_levels,
        dtype=dtype,
        compiled=compiled,
        parameters=sum(p.numel() for p in model.parameters()),
    )
    t0 = time.perf_counter()
    for name, step in (("forward", forward), ("forward_backward", train_step)):
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        times = time_steps(step, args.repeats, warmup, device)
        result[f"{name}_s"] = statistics.median(times)
        result[f"{name}_s_all"] = times
        if device.type == "cuda":
            result[f"{name}_peak_memory_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    result["wall_s"] = time.perf_counter() - t0
    if compiled:
        torch._dynamo.reset()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--hidden", type=int, default=128, help="latent size d (MLP hidden size too)")
    parser.add_argument("--repeats", type=int, default=3, help="timed steps per variant (median reported)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps before timing (+1 compiled)")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile variants")
    parser.add_argument("--scale", type=int, default=1, help="laminate_mesh scale (1: the paper's mesh)")
    parser.add_argument("--levels", type=int, nargs="+", default=[4, 1], help="num_levels variants (1: flat)")
    parser.add_argument("--dtypes", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    parser.add_argument("--k", type=int, default=3, help="contact neighbours per other component")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument(
        "--matmul-precision",
        default="highest",
        choices=["highest", "high", "medium"],
        help="torch.set_float32_matmul_precision ('high': TF32 on CUDA for the fp32 variants)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="default: benchmarks/results/model_<device>.json"
    )
    args = parser.parse_args()
    out = args.out or Path(f"benchmarks/results/model_{args.device}.json")
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.set_float32_matmul_precision(args.matmul_precision)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda, but CUDA is not available")

    h, num_components, contact_source = make_data(args.scale, max(args.levels), args.k)
    x_dict, e_dict = normalized_features(h, num_components)
    x_dict = {k: v.to(device) for k, v in x_dict.items()}
    e_dict = {k: v.to(device) for k, v in e_dict.items()}
    ei_dict = {k: v.to(device) for k, v in h.edge_index_dict.items()}
    data = (h, x_dict, e_dict, ei_dict, ampn_channels(num_components, NUM_GRIPPERS))
    levels = [
        dict(
            level=k,
            nodes=int(h.level(k).num_nodes),
            mesh_edges=int(h.mesh(k).edge_index.size(1)),
            contact_edges=int(h.contact(k).edge_index.size(1)),
            down_edges=int(h.down(k).edge_index.size(1)) if k + 1 < h.num_levels else 0,
        )
        for k in range(h.num_levels)
    ]
    print(f"hierarchy: {h.num_levels} levels, contact edges: {contact_source}")
    for lv in levels:
        print(
            f"  l{lv['level']}: {lv['nodes']} nodes, {lv['mesh_edges']} mesh, "
            f"{lv['contact_edges']} contact, {lv['down_edges']} down edges"
        )

    results = []
    for num_levels in args.levels:
        if num_levels > h.num_levels:
            print(f"skipping num_levels={num_levels}: the hierarchy has {h.num_levels} levels")
            continue
        for dtype in args.dtypes:
            for compiled in [False, True] if args.compile else [False]:
                r = run_variant(args, data, device, num_levels, dtype, compiled)
                results.append(r)
                mem = f"  peak {r['forward_backward_peak_memory_mb']:.0f} MB" if device.type == "cuda" else ""
                print(
                    f"{r['model']:>12} L={num_levels} {dtype:>4} {'compiled' if compiled else 'eager':>8}: "
                    f"fwd {r['forward_s']:.3f} s, fwd+bwd {r['forward_backward_s']:.3f} s{mem}",
                    flush=True,
                )

    header = f"{'model':>12} {'levels':>6} {'dtype':>5} {'mode':>8} {'fwd [s]':>9} {'fwd+bwd [s]':>11}"
    if device.type == "cuda":
        header += f" {'peak MB':>8}"
    print("\n" + header + "\n" + "-" * len(header))
    for r in results:
        mode = "compiled" if r["compiled"] else "eager"
        line = (
            f"{r['model']:>12} {r['num_levels']:>6} {r['dtype']:>5} {mode:>8} "
            f"{r['forward_s']:>9.3f} {r['forward_backward_s']:>11.3f}"
        )
        if device.type == "cuda":
            line += f" {r['forward_backward_peak_memory_mb']:>8.0f}"
        print(line)

    meta = dict(
        benchmark="model",
        device=args.device,
        device_name=device_name(device),
        machine=platform.machine(),
        threads=torch.get_num_threads(),
        torch=torch.__version__,
        hidden=args.hidden,
        matmul_precision=args.matmul_precision,
        repeats=args.repeats,
        warmup=args.warmup,
        scale=args.scale,
        contact_edges=contact_source,
        levels=levels,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(meta=meta, results=results), indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
