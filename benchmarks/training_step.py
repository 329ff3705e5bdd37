"""Benchmark: one quickstart training step (forward + backward + Adam) for model variants.

Batches of 4 cached training windows from a dataset folder, as ``torch-ampn fit`` with
``examples/configs/quickstart.yaml`` uses them. Every variant changes one setting of the
quickstart model; rounds are interleaved so that all variants see the same machine state.
``--compile`` adds the quickstart model with ``compile_network=True`` (its training step's
network under ``torch.compile(dynamic=True)``, as the quickstart config runs it; the first
step, which compiles, is reported separately). "quickstart" leaves out the config's
pushforward (``pushforward=0.5`` is the config: an extra forward pass on about half the
steps; ``pushforward=1`` on every step). Prints a table and writes JSON.

    python benchmarks/training_step.py data/default
    python benchmarks/training_step.py data/default --compile
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from torch_ampn.utils.threads import follow_free_cpu

from device_info import device_name  # benchmarks/device_info.py, beside this script

QUICKSTART = dict(
    hidden_channels=32, mlp_channels=32, num_levels=3, pre_layers=1, down_layers=1, solve_layers=1,
    post_layers=1, up_layers=1, contact_radius=12.0, contact_k=1, position_noise=1e-3, residual_noise=1e-4,
    correlated_noise=True,
)  # fmt: skip
VARIANTS: dict[str, dict] = {
    "quickstart": {},
    "contact_k=3": {"contact_k": 3},
    "solve_layers=4": {"solve_layers": 4},
    "hidden=48": {"hidden_channels": 48, "mlp_channels": 48},
    "hidden=64": {"hidden_channels": 64, "mlp_channels": 64},
    "pre/post_layers=2": {"pre_layers": 2, "post_layers": 2},
    "pushforward=0.5": {"pushforward": 0.5},
    "pushforward=1": {"pushforward": 1.0},
}


class QuickstartCase:
    """A model, its optimiser and a fixed list of batches for one variant."""

    def __init__(self, data_dir: str, settings: dict, num_batches: int, compile_network: bool) -> None:
        from torch_ampn.training import AMPNDataModule, NextStepLightningModule

        torch.manual_seed(0)
        kw = {**QUICKSTART, **settings}
        dm = AMPNDataModule(
            data_dir=data_dir, batch_size=4, contact_radius=kw["contact_radius"],
            contact_k=kw["contact_k"], cache_windows=True,
        )  # fmt: skip
        dm.setup("fit")
        self.model = NextStepLightningModule(**kw, compile_network=compile_network)
        self.model.fit_statistics(dm.statistics_samples(20))
        loader = iter(dm.train_dataloader())
        self.batches = [next(loader) for _ in range(num_batches)]
        self.optimizer = torch.optim.Adam(self.model.parameters(), 1e-4)
        self.compile_s = None
        if compile_network:  # the first step compiles (NextStepLightningModule.training_loss)
            start = time.perf_counter()
            self.step(self.batches[0])
            self.compile_s = time.perf_counter() - start

    def step(self, batch) -> None:
        loss = self.model.training_loss(self.model.training_inputs(batch.clone()))
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()

    def time_steps(self) -> float:
        """Seconds per step, the threads following the free CPU as in a fit (FollowFreeCpu)."""
        with follow_free_cpu() as threads:
            start = time.perf_counter()
            for batch in self.batches[1:]:
                threads.step()
                self.step(batch)
            return (time.perf_counter() - start) / (len(self.batches) - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data_dir", help="dataset folder (e.g. data/default)")
    parser.add_argument("--steps", type=int, default=12, help="timed steps per round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--compile", action="store_true", help="add the compiled quickstart network")
    parser.add_argument(
        "--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
        help="eager variants to time (quickstart is always included)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    names = ["quickstart"] + [n for n in args.variants if n != "quickstart"]
    cases = {name: QuickstartCase(args.data_dir, VARIANTS[name], args.steps + 1, False) for name in names}
    if args.compile:
        cases["quickstart, compiled"] = QuickstartCase(args.data_dir, {}, args.steps + 1, True)
    for case in cases.values():  # warm-up
        case.step(case.batches[0])
    times: dict[str, list[float]] = {name: [] for name in cases}
    for r in range(args.rounds):
        for name in list(cases) if r % 2 == 0 else list(cases)[::-1]:
            times[name].append(cases[name].time_steps())
    base = statistics.median(times["quickstart"])
    rows = []
    print(f"{'variant':<22} {'ms/step':>8} {'vs quickstart':>13}")
    for name, ts in times.items():
        median = statistics.median(ts)
        rows.append({"variant": name, "step_s": median, "relative": median / base, "rounds": ts,
                     "compile_s": cases[name].compile_s})  # fmt: skip
        print(f"{name:<22} {1e3 * median:>8.0f} {median / base:>12.2f}x")
    for name, case in cases.items():
        if case.compile_s is not None:
            print(f"{name}: first step (compiles) {case.compile_s:.0f} s")
    out = args.out or Path(__file__).parent / "results" / "training_step_cpu.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"torch": torch.__version__, "threads": torch.get_num_threads(), "machine": device_name("cpu")}
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
