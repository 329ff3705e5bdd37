"""Benchmark: wall time of a whole autoregressive rollout (50 steps), and where it goes.

The input is the paper-resolution quarter model (``StampFormingConfig.paper()``: 4 plies of
3,200 triangles, punch and die, 16,390 nodes, 4 levels) or the coarse default, as made by
``torch_ampn.sim.process_trajectory`` (tools on their prescribed path). The model is an
``AMPNSurrogate`` with the paper's sizes (d = 128, 15 layers) and untrained weights whose
decoder is zeroed, so plies stay put and every step does the full work: contact edges on
every level, features, normalisation, the V-cycle. Per step it reports the contact search
and the predictor separately (timed with device synchronisation), and the whole rollout
without the extra synchronisation. Prints a table and writes JSON.

    python benchmarks/rollout.py --device cpu --resolution coarse
    python benchmarks/rollout.py --device cuda --resolution paper --compile
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.data import HierarchyCache
from torch_ampn.nn import AMPNSurrogate
from torch_ampn.rollout import rollout
from torch_ampn.sim import StampFormingConfig, process_trajectory


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class Timed:
    """Wraps a callable and records its wall time per call (synchronising the device)."""

    def __init__(self, fn, device: torch.device) -> None:
        self.fn, self.device, self.seconds = fn, device, []

    def __call__(self, *args):
        sync(self.device)
        start = time.perf_counter()
        out = self.fn(*args)
        sync(self.device)
        self.seconds.append(time.perf_counter() - start)
        return out


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    cfg = StampFormingConfig.paper() if args.resolution == "paper" else StampFormingConfig()
    traj = process_trajectory(cfg, seed=0)
    levels = args.levels or (4 if args.resolution == "paper" else 3)
    hierarchy = HierarchyCache(None, max_levels=levels)(traj).to(device)
    surrogate = AMPNSurrogate(
        hidden_channels=args.hidden, mlp_channels=args.hidden, num_levels=levels, contact_radius=args.radius
    )
    surrogate.model.decoder.weight.data.zero_()
    surrogate.model.decoder.bias.data.zero_()
    surrogate.freeze_statistics()
    surrogate = surrogate.to(device).eval()
    if args.compile:
        surrogate.diffusion.model = torch.compile(surrogate.diffusion.model, dynamic=True)
    generator = torch.Generator(device=device).manual_seed(0)

    def predictor(data):
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16):
            return surrogate.predict_residual(data, generator)

    # warm-up (compilation, caches), then timed rollouts
    rollout(predictor, traj, hierarchy, surrogate.contact, num_steps=min(3, args.steps), device=device)
    totals = []
    for _ in range(args.repeats):
        sync(device)
        start = time.perf_counter()
        rollout(predictor, traj, hierarchy, surrogate.contact, num_steps=args.steps, device=device)
        sync(device)
        totals.append(time.perf_counter() - start)
    contact, predict = Timed(surrogate.contact, device), Timed(predictor, device)
    rollout(predict, traj, hierarchy, contact, num_steps=args.steps, device=device)
    return dict(
        device=torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
        threads=torch.get_num_threads(),
        resolution=args.resolution,
        nodes=traj.num_nodes,
        levels=hierarchy.num_nodes_per_level(),
        steps=args.steps,
        hidden=args.hidden,
        compile=args.compile,
        bf16=args.bf16,
        rollout_s=statistics.median(totals),
        contact_ms_per_step=1e3 * statistics.median(contact.seconds),
        predict_ms_per_step=1e3 * statistics.median(predict.seconds),
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--resolution", choices=("coarse", "paper"), default="paper")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--levels", type=int, default=None)
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--radius", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--bf16", action="store_true")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    result = run(args)
    head = f"{'resolution':>10} {'nodes':>7} {'device':>24} {'compile':>7} {'bf16':>5} {'rollout [s]':>12} "
    head += f"{'contact [ms/step]':>18} {'predict [ms/step]':>18}"
    print(head)
    print(
        f"{result['resolution']:>10} {result['nodes']:>7} {result['device'][:24]:>24} "
        f"{result['compile']!s:>7} "
        f"{result['bf16']!s:>5} {result['rollout_s']:>12.3f} {result['contact_ms_per_step']:>18.1f} "
        f"{result['predict_ms_per_step']:>18.1f}"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"rollout_{args.device.split(':')[0]}_{args.resolution}{'_compiled' if args.compile else ''}.json"
    path = args.out / name
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2))
    tmp.replace(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
