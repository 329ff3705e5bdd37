"""Benchmark: a whole autoregressive rollout, plain path against the fast path, and the simulator.

For one resolution it times, side by side in one process:

* ``plain``: :func:`torch_ampn.rollout.rollout` with ``surrogate.predict_residual`` (eager),
  with its per-step split into contact search and predictor;
* ``fast``: :class:`torch_ampn.rollout.fast.FastRollout` (compiled unless ``--no-compile``),
  with its split into contact searches and the compiled step (contact selection, features,
  network), for batch sizes ``--batch-sizes`` (settings per second);
* ``simulator``: the embedded simulator (``torch_ampn.sim.simulate_batch``, compiled) making
  the same trajectory: the speed-up column is its time over a rollout's;
* the largest deviation between the two paths' positions (same noise), and the peak memory.

Models: ``--resolution coarse`` uses the quickstart network (d = 32, 5 layers, 3 levels,
r = 12 mm, k = 1, read from ``examples/configs/quickstart.yaml``); ``paper`` the paper's
(d = 128, 15 layers, 4 levels, r = 3 mm, k = 3) on the paper-resolution mesh; ``--mesh-scale
S`` refines the paper mesh to about ``S`` times the nodes. Weights are untrained but the
normalisation statistics are real (from the benchmark trajectory), so plies move by about a
training residual per step and the contact edges change as in a rollout. The trajectory is
``process_trajectory`` (tools on their path, the gripper setting of the seed). Prints a table
and writes JSON (atomically).

    python benchmarks/rollout.py --resolution coarse                    # the quickstart model
    python benchmarks/rollout.py --resolution paper --steps 10 --batch-sizes 1
    python benchmarks/rollout.py --device cuda --resolution paper --mesh-scale 4
    python benchmarks/rollout.py --quick                                # a smoke test (seconds)
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import resource
import statistics
import time
from pathlib import Path

import torch
import yaml

from torch_ampn.data import HierarchyCache, step_sample
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.rollout import rollout
from torch_ampn.rollout.fast import FastRollout
from torch_ampn.sim import StampFormingConfig, process_trajectory, simulate_batch

from device_info import device_name  # benchmarks/device_info.py, beside this script

ROOT = Path(__file__).resolve().parent.parent
NETWORK_KEYS = ("hidden_channels", "mlp_channels", "num_levels", "pre_layers", "down_layers", "solve_layers",
                "post_layers", "up_layers", "contact_radius", "contact_k")  # fmt: skip


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class Timed:
    """Wraps a callable and records its wall time per call (synchronising the device) in ``seconds``.

    ``sink``: a list to record into (several wrapped callables can share one).
    """

    def __init__(self, fn, device: torch.device, sink: list | None = None) -> None:
        self.fn, self.device, self.seconds = fn, device, [] if sink is None else sink

    def __call__(self, *args, **kwargs):
        sync(self.device)
        start = time.perf_counter()
        out = self.fn(*args, **kwargs)
        sync(self.device)
        self.seconds.append(time.perf_counter() - start)
        return out


def setting(args: argparse.Namespace) -> tuple[StampFormingConfig, dict]:
    """Simulator config and network settings of the benchmark."""
    if args.resolution == "coarse":
        model = yaml.safe_load((ROOT / "examples/configs/quickstart.yaml").read_text())["model"]["init_args"]
        cfg = StampFormingConfig()
    else:
        model = yaml.safe_load((ROOT / "examples/configs/paper.yaml").read_text())["model"]["init_args"]
        scale = math.sqrt(args.mesh_scale)
        base = StampFormingConfig.paper()
        cfg = StampFormingConfig.paper(
            ply_cells=round(base.ply_cells * scale),
            punch_cells=tuple(round(c * scale) for c in base.punch_cells),
            die_cells=tuple(round(c * scale) for c in base.die_cells),
        )
    network = {k: model[k] for k in NETWORK_KEYS if k in model}
    if args.quick:
        cfg = StampFormingConfig(ply_cells=6, punch_cells=(5, 5), die_cells=(6, 6), num_steps=args.steps)
        network.update(hidden_channels=16, mlp_channels=16, num_levels=2)
    return StampFormingConfig.from_dict({**cfg.to_dict(), "num_steps": args.steps}), network


def build_surrogate(trajectory, hierarchy, network: dict, device: torch.device) -> AMPNSurrogate:
    torch.manual_seed(0)
    components = int(trajectory.component.max()) + 1
    s = AMPNSurrogate(num_components=components, num_grippers=trajectory.num_grippers, **network)
    for t in range(1, trajectory.num_steps + 1, max(trajectory.num_steps // 10, 1)):
        s.accumulate_statistics(s.contact(step_sample(trajectory, t, hierarchy)))
    s.freeze_statistics()
    return s.to(device).eval()


def time_plain(s, traj, hierarchy, device, repeats) -> dict:
    g = torch.Generator(device=device)
    totals = []
    for _ in range(repeats):
        g.manual_seed(0)
        sync(device)
        start = time.perf_counter()
        pred = rollout(lambda d: s.predict_residual(d, g), traj, hierarchy, s.contact, device=device)
        sync(device)
        totals.append(time.perf_counter() - start)
    contact, predict = Timed(s.contact, device), Timed(lambda d: s.predict_residual(d, g), device)
    g.manual_seed(0)
    rollout(predict, traj, hierarchy, contact, device=device)
    steps = traj.num_steps
    return {
        "seconds": statistics.median(totals),
        "phases_ms_per_step": {
            "contact": 1e3 * sum(contact.seconds) / steps,
            "network": 1e3 * sum(predict.seconds) / steps,
        },
        "pred": pred,
    }  # fmt: skip


def time_fast(s, trajs, hierarchy, device, repeats, compile: bool, candidates: str = "auto") -> dict:
    b = len(trajs)
    start = time.perf_counter()
    fast = FastRollout(s, hierarchy, batch_size=b, compile=compile, device=device, candidates=candidates)
    gens = [torch.Generator(device=device) for _ in range(b)]

    def run():
        for g in gens:
            g.manual_seed(0)
        return fast(trajs, gens)

    pred = run()  # compiles
    setup = time.perf_counter() - start
    totals = []
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        pred = run()
        sync(device)
        totals.append(time.perf_counter() - start)
    timers: dict[str, list[float]] = {"search": []}
    for c in fast.candidates:
        c.build = Timed(c.build, device, timers["search"])
    if s.diffusion_steps == 1:  # one compiled graph: selection, features, network
        timers["step"] = []
        fast._fused = Timed(fast._fused, device, timers["step"])  # compiled or eager
    else:
        timers["inputs"], timers["network"] = [], []
        fast._inputs = Timed(fast._inputs, device, timers["inputs"])
        fast._residual = Timed(fast._residual, device, timers["network"])
    run()
    steps = trajs[0].num_steps
    return {
        "seconds": statistics.median(totals),
        "first_call_seconds": setup,
        "compiled": fast.compiled,
        "searches_per_level": [c.searches for c in fast.candidates],
        "candidate_modes": [c.mode for c in fast.candidates],
        "phases_ms_per_step": {k: 1e3 * sum(v) / steps for k, v in timers.items()},
        "pred": pred,
    }


def time_simulator(cfg: StampFormingConfig, seed: int) -> float:
    simulate_batch(cfg, [seed], compile=True)  # compile outside the timing
    start = time.perf_counter()
    simulate_batch(cfg, [seed], compile=True)
    return time.perf_counter() - start


def peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    cfg, network = setting(args)
    trajs = [process_trajectory(cfg, seed=i) for i in range(max(args.batch_sizes))]
    levels = network.get("num_levels", 4)
    cache = HierarchyCache(None, max_levels=levels)
    hierarchy = cache(trajs[0]).to(device)
    s = build_surrogate(trajs[0], cache(trajs[0]), network, device)
    result = {
        "date": datetime.date.today().isoformat(),
        "device": device_name(device),
        "threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
        "load_average_before": os.getloadavg(),
        "resolution": args.resolution,
        "mesh_scale": args.mesh_scale,
        "nodes": trajs[0].num_nodes,
        "levels": hierarchy.num_nodes_per_level()[:levels],
        "steps": args.steps,
        "network": network,
        "torch": torch.__version__,
    }
    plain = time_plain(s, trajs[0], hierarchy, device, args.repeats)
    result["plain"] = {k: v for k, v in plain.items() if k != "pred"}
    result["fast"] = {}
    for b in args.batch_sizes:
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        fast = time_fast(s, trajs[:b], hierarchy, device, args.repeats, not args.no_compile, args.candidates)
        entry = {k: v for k, v in fast.items() if k != "pred"}
        entry["settings_per_second"] = b / fast["seconds"]
        entry["peak_memory_mb"] = peak_memory_mb(device)
        if b == 1:
            entry["max_deviation_mm"] = float((fast["pred"][0] - plain["pred"]).abs().max())
        if args.bf16 and b == 1 and device.type == "cuda":
            with torch.autocast("cuda", dtype=torch.bfloat16):
                bf = time_fast(
                    s, trajs[:1], hierarchy, device, args.repeats, not args.no_compile, args.candidates
                )
            deviation = float((bf["pred"][0] - plain["pred"]).abs().max())
            entry["bf16"] = {"seconds": bf["seconds"], "max_deviation_mm": deviation}
        result["fast"][str(b)] = entry
    if not args.no_simulator:
        result["simulator_seconds"] = time_simulator(cfg, seed=0)
    result["load_average_after"] = os.getloadavg()
    return result


def table(result: dict) -> str:
    sim = result.get("simulator_seconds")
    rows = [
        f"{result['resolution']} mesh, {result['nodes']} nodes, levels {result['levels']}, "
        f"{result['steps']} steps, {result['device']} ({result['threads']} threads), {result['date']}",
        f"{'path':>14} {'B':>3} {'rollout [s]':>12} {'settings/s':>11} {'vs plain':>9} "
        f"{'vs simulator':>13}  phases [ms/step]",
    ]
    plain = result["plain"]["seconds"]

    def row(name, b, seconds, phases):
        speed = f"{sim / (seconds / b):.1f}x" if sim else "-"
        split = ", ".join(f"{k} {v:.1f}" for k, v in phases.items())
        gain = plain / (seconds / b)
        return f"{name:>14} {b:>3} {seconds:>12.3f} {b / seconds:>11.2f} {gain:>8.1f}x {speed:>13}  {split}"

    rows.append(row("plain", 1, plain, result["plain"]["phases_ms_per_step"]))
    for b, entry in result["fast"].items():
        name = "fast" + ("" if entry["compiled"] else " (eager)")
        rows.append(row(name, int(b), entry["seconds"], entry["phases_ms_per_step"]))
    if sim:
        rows.append(f"{'simulator':>14} {1:>3} {sim:>12.3f}")
    fast1 = result["fast"].get("1")
    if fast1:
        rows.append(
            f"fast vs plain: largest deviation {fast1['max_deviation_mm']:.2e} mm; first call (compile) "
            f"{fast1['first_call_seconds']:.1f} s; searches per level {fast1['searches_per_level']} "
            f"({'/'.join(fast1['candidate_modes'])})"
        )
    return "\n".join(rows)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--resolution", choices=("coarse", "paper"), default="coarse")
    parser.add_argument(
        "--mesh-scale", type=float, default=1.0, help="paper mesh refined to ~S times the nodes"
    )
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-compile", action="store_true", help="the fast path without torch.compile")
    parser.add_argument(
        "--candidates",
        default="auto",
        choices=["auto", "dense", "patches", "verlet", "search"],
        help="contact candidates of every level (FastRollout's candidates)",
    )
    parser.add_argument("--bf16", action="store_true", help="also the fast path under bf16 autocast (CUDA)")
    parser.add_argument("--no-simulator", action="store_true")
    parser.add_argument(
        "--quick", action="store_true", help="tiny mesh and network, a few steps: a smoke test"
    )
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    if args.quick:
        args.steps, args.batch_sizes, args.repeats = min(args.steps, 5), [1, 2], 1
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    result = run(args)
    print(table(result))
    args.out.mkdir(parents=True, exist_ok=True)
    tag = f"{args.device.split(':')[0]}_{args.resolution}" + (
        f"_x{args.mesh_scale:g}" if args.mesh_scale != 1 else ""
    )
    path = args.out / f"rollout_{tag}{'_quick' if args.quick else ''}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
