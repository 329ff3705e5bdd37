"""Benchmark: speed when other processes share the cores, with and without a thread mechanism.

    python benchmarks/under_load.py data/default
    python benchmarks/under_load.py data/default --workloads simulate --mechanisms default passive

Three workloads, each in a fresh process (OpenMP reads its settings when torch starts):

* ``train``: 10 quickstart training steps (batches of 4 windows of ``DATA``, eager),
* ``rollout``: a 50-step fast rollout of a quickstart-sized surrogate (compiled; untrained
  weights cost the same),
* ``simulate``: one coarse trajectory of the embedded simulator (compiled).

Each runs quiet, beside one and beside two busy processes (pure-Python loops that this
script starts and stops, one core each), under each mechanism (:data:`MECHANISMS`: the
environment a process starts with). Set-up and compiling (warm cache) are outside the
timed part. A run that exceeds ``--timeout`` is reported as such. Prints a table (seconds
and the ratio to the same mechanism's quiet time) and writes JSON after every run.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Environments a workload starts with. ``AMPN_THREADS=off`` turns the package's own choice
#: off, so ``default`` is torch as it comes and ``package`` what the package's loops do
#: (:func:`torch_ampn.utils.threads.follow_free_cpu`: torch's spinning threads, as many as the
#: cores other processes leave free).
MECHANISMS: dict[str, dict[str, str]] = {
    "default": {"AMPN_THREADS": "off"},
    "passive": {"AMPN_THREADS": "off", "OMP_WAIT_POLICY": "PASSIVE"},
    "spin=10000": {"AMPN_THREADS": "off", "GOMP_SPINCOUNT": "10000"},
    "spin=1000": {"AMPN_THREADS": "off", "GOMP_SPINCOUNT": "1000"},
    "spin=300": {"AMPN_THREADS": "off", "GOMP_SPINCOUNT": "300"},
    "spin=100": {"AMPN_THREADS": "off", "GOMP_SPINCOUNT": "100"},
    "threads=1": {"AMPN_THREADS": "off", "OMP_NUM_THREADS": "1"},
    # sleeping threads, and compiled (Inductor) kernels run serially below this many elements
    # per thread (Inductor's default: 512), so that small kernels wake no thread
    **{
        f"passive+chunk={n}": {
            "AMPN_THREADS": "off",
            "OMP_WAIT_POLICY": "PASSIVE",
            "TORCHINDUCTOR_CPP_MIN_CHUNK_SIZE": str(n),
        }
        for n in (4096, 16384, 65536)
    },  # fmt: skip
    "package": {},
}
#: Environment variables a mechanism may set; removed before each run so that none leaks in.
CONTROLLED = ("AMPN_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")
CONTROLLED += ("TORCHINDUCTOR_CPP_MIN_CHUNK_SIZE",)
WORKLOADS = ("train", "rollout", "simulate")
BUSY = "import time\nend = time.monotonic() + {limit}\nwhile time.monotonic() < end:\n    pass\n"


def worker(name: str, data_dir: str) -> dict:
    """Run one workload in this process; its timed seconds and thread settings."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import torch

    from torch_ampn.utils.threads import GOVERNOR, follow_free_cpu

    if name == "train":
        from training_step import QuickstartCase

        case = QuickstartCase(data_dir, {}, num_batches=11, compile_network=False)
        with follow_free_cpu() as threads:  # warm-up: a second of steps, as a fit's first second
            end = time.perf_counter() + 1.0
            while time.perf_counter() < end:
                threads.step()
                case.step(case.batches[0])
        seconds = case.time_steps() * 10
    elif name == "rollout":
        from rollout import build_surrogate, time_fast

        from torch_ampn.data import HierarchyCache
        from torch_ampn.sim import StampFormingConfig, process_trajectory

        traj = process_trajectory(StampFormingConfig(), seed=0)
        hierarchy = HierarchyCache(None, max_levels=3)(traj)
        network = dict(hidden_channels=32, mlp_channels=32, num_levels=3, contact_radius=12.0, contact_k=1)
        s = build_surrogate(traj, hierarchy, network, torch.device("cpu"))
        seconds = time_fast(s, [traj], hierarchy, torch.device("cpu"), repeats=3, compile=True)["seconds"]
    elif name == "simulate":
        from rollout import time_simulator

        from torch_ampn.sim import StampFormingConfig

        seconds = time_simulator(StampFormingConfig(), seed=0)
    else:
        raise ValueError(f"workload must be one of {WORKLOADS}, got {name!r}")
    from device_info import device_name

    env = {k: os.environ[k] for k in CONTROLLED if k in os.environ}
    threads = torch.get_num_threads()
    changes = [n for _, n in GOVERNOR.history]  # the thread counts the package's loops chose, in order
    looks = [[round(others, 2), n] for _, others, n in GOVERNOR.looks][-60:]  # others' cores, threads
    return {"seconds": seconds, "threads": threads, "thread_changes": changes, "last_looks": looks,
            "env": env, "processor": device_name("cpu")}  # fmt: skip


def start_busy(count: int, limit: float) -> list[subprocess.Popen]:
    """``count`` busy processes, each ending by itself after ``limit`` seconds at the latest."""
    return [subprocess.Popen([sys.executable, "-c", BUSY.format(limit=limit)]) for _ in range(count)]


def stop(processes: list[subprocess.Popen]) -> None:
    """Kill and reap ``processes``."""
    for p in processes:
        p.kill()
    for p in processes:
        p.wait()


def measure(
    workload: str, mechanism: str, busy: int, args: argparse.Namespace, timeout: float | None
) -> dict:
    """One run of ``workload`` in a fresh process under ``mechanism`` beside ``busy`` busy processes.

    A run past ``timeout`` seconds is killed with its whole process group (Inductor's compiler
    processes included), so that nothing it started loads the next run.
    """
    env = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    env.update(MECHANISMS[mechanism])
    command = [sys.executable, __file__, args.data_dir, "--worker", workload]
    others = start_busy(busy, (timeout or 3600) + 30)
    start = time.perf_counter()
    run = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           start_new_session=True)  # fmt: skip
    try:
        stdout, stderr = run.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)
        run.communicate()
        return {"timed_out": True, "wall_seconds": time.perf_counter() - start}
    finally:
        stop(others)
    if run.returncode != 0:
        raise RuntimeError(f"{workload} under {mechanism} failed:\n{stderr[-2000:]}")
    result = json.loads(stdout.strip().splitlines()[-1])
    return {**result, "timed_out": False, "wall_seconds": time.perf_counter() - start}


def write_json(path: Path, payload: dict) -> None:
    """Write ``payload`` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, path)


def _median(runs: list[dict]) -> dict:
    """The median seconds of ``runs`` of one cell, or a timed-out row where any run timed out."""
    late = [r for r in runs if r["timed_out"]]
    if late:
        return {"timed_out": True, "wall_seconds": min(r["wall_seconds"] for r in late)}
    return {"timed_out": False, "seconds": statistics.median(r["seconds"] for r in runs)}


def _cell(row: dict | None, quiet: float | None) -> str:
    """Seconds of one cell, with the ratio to ``quiet`` when given."""
    if row is None:
        return "-"
    if row["timed_out"]:
        return f"> {row['wall_seconds']:.0f} (timed out)"
    ratio = f" ({row['seconds'] / quiet:.1f}x)" if quiet else ""
    return f"{row['seconds']:.2f}{ratio}"


def table(rows: list[dict]) -> str:
    """Markdown table: median seconds quiet, beside 1 and 2 busy processes, and the ratios to quiet."""
    lines = [
        "| workload | mechanism | quiet [s] | 1 busy [s] (x quiet) | 2 busy [s] (x quiet) | runs |",
        "|---|---|---:|---:|---:|---:|",
    ]
    runs: dict[tuple[str, str], dict[int, list[dict]]] = {}
    for r in rows:
        runs.setdefault((r["workload"], r["mechanism"]), {}).setdefault(r["busy"], []).append(r)
    for (workload, mechanism), by_busy in runs.items():
        cells = {busy: _median(rs) for busy, rs in by_busy.items()}
        quiet = cells[0].get("seconds") if 0 in cells else None
        shown = [_cell(cells.get(busy), quiet if busy else None) for busy in (0, 1, 2)]
        count = max(len(rs) for rs in by_busy.values())
        lines.append(f"| {workload} | {mechanism} | {' | '.join(shown)} | {count} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Parse arguments; run the grid (or, with ``--worker``, one workload) and report."""
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("data_dir", help="dataset folder for the training windows (e.g. data/default)")
    parser.add_argument("--workloads", nargs="+", choices=WORKLOADS, default=list(WORKLOADS))
    parser.add_argument("--mechanisms", nargs="+", choices=list(MECHANISMS), default=list(MECHANISMS))
    parser.add_argument("--busy", nargs="+", type=int, default=[0, 1, 2], help="busy processes beside")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per run")
    parser.add_argument(
        "--repeats", type=int, default=1, help="interleaved repeats of the grid (median shown)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/under_load_cpu.json")
    parser.add_argument("--worker", choices=WORKLOADS, help=argparse.SUPPRESS)
    parser.add_argument("--table", type=Path, help="only print the table of this JSON file")
    args = parser.parse_args(argv)
    if args.table:
        print(table(json.loads(args.table.read_text())["rows"]))
        return
    if args.worker:
        print(json.dumps(worker(args.worker, args.data_dir)))
        return
    # warm the compile cache outside the timed grid, however long it takes: once per kernel
    # variant (mechanisms that set Inductor's chunk size or the thread count compile kernels of
    # their own: the thread count is written into the generated code; the package compiles on
    # torch's count and changes it only between kernels)
    kernel_settings = ("TORCHINDUCTOR_CPP_MIN_CHUNK_SIZE", "OMP_NUM_THREADS")

    def kernel_variant(mechanism: str) -> tuple:
        return tuple(MECHANISMS[mechanism].get(k) for k in kernel_settings)

    variants = {kernel_variant(m): m for m in reversed(args.mechanisms)}
    for workload in args.workloads:
        for mechanism in variants.values():
            print(f"{workload:<9} warming the compile cache ({mechanism})", flush=True)
            measure(workload, mechanism, 0, args, timeout=None)
    meta = {"date": datetime.date.today().isoformat(), "cpus": os.cpu_count(), "load_before": os.getloadavg()}
    rows: list[dict] = []
    for repeat in range(args.repeats):  # interleaved, so that a slow spell of the machine hits all cells
        for workload in args.workloads:
            for busy in args.busy:
                for mechanism in args.mechanisms:
                    row = {"workload": workload, "mechanism": mechanism, "busy": busy, "repeat": repeat}
                    row.update(measure(workload, mechanism, busy, args, args.timeout))
                    rows.append(row)
                    shown = "timed out" if row["timed_out"] else f"{row['seconds']:.2f} s"
                    print(f"{workload:<9} {mechanism:<10} beside {busy} busy: {shown}", flush=True)
                    write_json(args.out, {"meta": meta, "rows": rows})
    print(table(rows))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
