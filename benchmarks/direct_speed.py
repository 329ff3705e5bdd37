"""Seconds per setting for the formed part: the direct model against the embedded simulator.

    python benchmarks/direct_speed.py --checkpoint CKPT --settings 32 --batch 1 2 4 8 16 \
        --out benchmarks/results/direct/speed.json

For ``--settings`` gripper settings (random, seeded) at each ``--resolutions`` entry: the direct
model's final state (``predict_direct(final=True)``, ``--batch`` settings per network pass, each
batch size in turn, eager; one warm-up batch first; the fastest is the row's) and, at the coarse
resolution, the simulator's whole run of the same settings (compiled, batches of 16, a warm-up
batch of 2 first so that compiling is not counted), side by side in one process. The simulator
at the paper resolution takes about 11 minutes per setting on 2 cores;
``--paper-simulator-json`` reads its seconds per trajectory from ``benchmarks/simulate.py``'s
JSON (its date and machine are printed with it) instead of running it. Without ``--checkpoint``
the direct model has the config's architecture and untrained weights (the cost is the same; so
at the paper resolution, where a trained model's mean base does not fit the mesh); the time
includes building each setting's input (features, contact edges of the initial state), not the
hierarchy (once per mesh, printed). ``--no-simulator`` times the direct model alone. Prints a
table and writes JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path

import torch
import yaml

from torch_ampn.data import HierarchyCache, direct_sample
from torch_ampn.rollout.direct import predict_direct
from torch_ampn.sim import StampFormingConfig, process_trajectory, simulate_batch
from torch_ampn.utils.io import atomic_write_text

CONFIG = Path(__file__).resolve().parents[1] / "examples" / "configs" / "direct.yaml"


def random_settings(n: int, seed: int) -> list[tuple[list[float], list[float]]]:
    """``n`` gripper settings: edge fractions in [0.2, 0.8], forces in [20, 100] N (two grippers)."""
    g = torch.Generator().manual_seed(seed)
    where = 0.2 + 0.6 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    force = 20.0 + 80.0 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    return [(w.tolist(), f.tolist()) for w, f in zip(where, force, strict=True)]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--resolutions", nargs="+", choices=["coarse", "paper"], default=["coarse", "paper"])
    parser.add_argument("--settings", type=int, default=32)
    parser.add_argument("--batch", type=int, nargs="+", default=[4], help="settings per pass (several: each)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-simulator", action="store_true", help="time the direct model alone")
    parser.add_argument(
        "--paper-simulator-json", type=Path, default=Path("benchmarks/results/simulate_paper_v3.json")
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/direct/speed.json"))
    args = parser.parse_args()
    rows = []
    settings = random_settings(args.settings, args.seed)
    for resolution in args.resolutions:
        cfg = StampFormingConfig() if resolution == "coarse" else StampFormingConfig.paper()
        # a trained model's mean base belongs to its mesh: other resolutions take the architecture untrained
        checkpoint = args.checkpoint if resolution == "coarse" else None
        model = load_model(checkpoint, cfg)
        trajs = [process_trajectory(cfg, w, f) for w, f in settings]
        start = time.perf_counter()
        hierarchy = HierarchyCache(None, max_levels=model.num_levels)(trajs[0])
        hierarchy_seconds = time.perf_counter() - start
        by_batch = {}  # settings per pass -> seconds per setting
        with torch.inference_mode():
            for batch in args.batch:
                predict_direct(model, trajs[:batch], hierarchy, batch_size=batch, final=True)  # warm-up
                start = time.perf_counter()
                predict_direct(model, trajs, hierarchy, batch_size=batch, final=True)
                by_batch[batch] = (time.perf_counter() - start) / len(trajs)
        fastest = min(by_batch, key=by_batch.__getitem__)
        direct = by_batch[fastest]
        row = {
            "resolution": resolution,
            "nodes": trajs[0].num_nodes,
            "settings": len(trajs),
            "batch": fastest,
            "direct_seconds_per_setting": direct,
            "direct_seconds_per_setting_by_batch": by_batch,
            "hierarchy_seconds_once_per_mesh": hierarchy_seconds,
            "weights": "trained" if checkpoint is not None else "untrained (the config's architecture)",
        }
        if not args.no_simulator:
            row.update(simulator_time(resolution, cfg, settings, args.paper_simulator_json))
        if "simulator_seconds_per_setting" in row:
            row["speed_up"] = row["simulator_seconds_per_setting"] / direct
        rows.append(row)
        print(json.dumps(row))
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
        "checkpoint": str(args.checkpoint) if args.checkpoint else None,
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(result, indent=2))
    print(f"{'resolution':<11}{'nodes':>8}{'batch':>6}{'direct s':>10}{'simulator s':>13}{'speed-up':>10}")
    for r in rows:
        sim = r.get("simulator_seconds_per_setting", float("nan"))
        for batch, seconds in r["direct_seconds_per_setting_by_batch"].items():
            print(
                f"{r['resolution']:<11}{r['nodes']:>8}{batch:>6}{seconds:>10.3f}{sim:>13.2f}"
                f"{sim / seconds:>10.1f}"
            )


def simulator_time(resolution: str, cfg: StampFormingConfig, settings: list, recorded_json: Path) -> dict:
    """The simulator's seconds per setting and their source: measured (coarse) or from ``recorded_json``."""
    if resolution == "coarse":
        simulate_batch(cfg, [0, 1], settings=settings[:2], compile=True)  # compile, not counted
        start = time.perf_counter()
        for i in range(0, len(settings), 16):
            part = settings[i : i + 16]
            simulate_batch(cfg, list(range(i, i + len(part))), settings=part, compile=True)
        seconds = (time.perf_counter() - start) / len(settings)
        return {"simulator_seconds_per_setting": seconds, "simulator_source": "measured here, side by side"}
    if not recorded_json.is_file():
        return {}
    recorded = json.loads(recorded_json.read_text())
    runs = [r for r in recorded.get("results", []) if r.get("resolution") == "paper"]
    per = [r.get("first_run_seconds_per_trajectory", r["seconds_per_trajectory"]) for r in runs]
    if not per:
        return {}
    meta = recorded.get("meta", {})
    return {
        "simulator_seconds_per_setting": min(per),
        "simulator_source": f"{recorded_json} ({meta.get('date', 'undated')}, {meta.get('device', '')})",
    }


def load_model(checkpoint: Path | None, cfg: StampFormingConfig):
    """The trained direct surrogate, or the config's architecture with one setting's statistics."""
    if checkpoint is not None:
        from torch_ampn.training import load_module

        return load_module(checkpoint).surrogate.eval()
    from torch_ampn.training import DirectLightningModule

    model = DirectLightningModule(**yaml.safe_load(CONFIG.read_text())["model"]["init_args"]).surrogate
    traj = process_trajectory(cfg, [0.5, 0.5], [50.0, 50.0])
    sample = model.contact(direct_sample(traj, HierarchyCache(None, max_levels=model.num_levels)(traj)))
    model.accumulate_statistics(sample)  # the cost does not depend on the statistics
    model.freeze_statistics()
    return model.eval()


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()
    main()
