"""The seed paper's Table 1 on our data: AMPN vs ROBIN K = 5/10/20, hierarchy vs flat, contact variants.

Every variant is one base config (``examples/configs/quickstart.yaml`` for ``--resolution
coarse``, ``paper.yaml`` for ``paper``) with one change, trained for a fixed number of steps
(``--steps``, not a time limit) and tested on the same test trajectories, for each seed:

    ampn            AMPN (K = 1), the base config
    robin5/10/20    ROBIN with K = 5, 10, 20 diffusion steps (``model.diffusion_steps``), conventional
                    inference: K denoising steps per time step
    flat            a flat MeshGraphNet (``model.num_levels 1``: Pre, Solve, Post on the fine mesh)
    radius          plain-radius contact edges (every node within r, any component)
    static_contact  contact edges built once from the initial state and kept (ROBIN's choice)
    k3              the paper's k = 3 contact neighbours (only where the base uses another k)
    prior           the AMPN reading the POD + GP prediction as input features (not in the paper:
                    ``model.prior_features``, ``data.prior pod_gp``; plain-path rollouts)
    physicsnemo_hybrid      the peers' own code (not in the default list; ``source
    physicsnemo_bsms        scripts/install_peers.sh`` first): NVIDIA PhysicsNeMo's
    physicsnemo_hybrid_eq   HybridMeshGraphNet (mesh + world edges) and BiStrideMeshGraphNet
    physicsnemo_bsms_eq     (BSMS-GNN) behind benchmarks/peers.py's adapters, PhysicsNeMo's
                    defaults scaled as the quickstart scales the paper's network (width 128 -> 32,
                    15 message-passing blocks -> 5: 84,771 and 99,139 parameters); ``_eq``: the
                    width that gives about the AMPN's 70,851 parameters of the quickstart recipe
                    (d = 29: 70,038; d = 27: 71,364). Plain-path rollouts, eager training.

A cell (variant, seed) runs ``torch-ampn fit`` and ``torch-ampn test`` in subprocesses, then
measures in this process: the rollout of one test trajectory for the figures, the contact
edges per step on the true test states, and the embedded simulator's own time for the same
test trajectories (compiled, the faster of one at a time and all at once). It writes
``<results>/<variant>_seed<k>.json`` atomically when it is complete; a rerun skips finished
cells, and a fit that was stopped resumes from its ``last.ckpt``. ``--report`` builds the
table (printed, ``table.md``, ``table.json``) and the figures from whatever cells exist.
``--timings`` times every variant's rollout (plain and fast path, from the weights a cell
saved) and the simulator side by side on one test trajectory, writes ``timings.json``, and
the table takes its rollout and speed-up columns from there (run it on an idle machine).

    python benchmarks/compare.py                             # every cell of the CPU grid (hours)
    python benchmarks/compare.py --variants ampn flat --seeds 0
    python benchmarks/compare.py --report
    python benchmarks/compare.py --timings                   # side-by-side rollout times
    python benchmarks/compare.py --resolution paper --device cuda --steps 20000   # the GPU grid
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import datetime
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch
import yaml

from device_info import device_name  # benchmarks/device_info.py, beside this script

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # benchmarks.peers, the peers' adapters, for checkpoints of their cells
    sys.path.insert(0, str(ROOT))
STATE_FRACTIONS = (0.7, 0.9, 1.0)  # the process times of the paper's Fig. 2 and Fig. 3


@dataclasses.dataclass(frozen=True)
class Variant:
    """One row of the table: a label and the config keys it changes (``section.key`` -> value)."""

    label: str
    changes: dict[str, Any]


VARIANTS = {
    "ampn": Variant("AMPN (K = 1)", {}),
    "robin5": Variant("ROBIN, K = 5", {"model.diffusion_steps": 5}),
    "robin10": Variant("ROBIN, K = 10", {"model.diffusion_steps": 10}),
    "robin20": Variant("ROBIN, K = 20", {"model.diffusion_steps": 20}),
    "flat": Variant("flat MeshGraphNet (1 level)", {"model.num_levels": 1}),
    "radius": Variant("AMPN, plain-radius contact edges", {"model.contact_mode": "radius"}),
    "static_contact": Variant(
        "AMPN, contact edges of the initial state", {"model.contact_positions": "initial"}
    ),
    "k3": Variant("AMPN, k = 3 contact neighbours", {"model.contact_k": 3}),
    "prior": Variant(
        "AMPN correcting the POD + GP prior", {"model.prior_features": True, "data.prior": "pod_gp"}
    ),
}


def _peer(label: str, cls: str, **options: Any) -> Variant:
    """A PhysicsNeMo network in place of the AMPN (benchmarks/peers.py), fine level only, eager."""
    return Variant(
        label,
        {
            "model.network_class": f"benchmarks.peers:{cls}",
            "model.network_options": options,
            "model.num_levels": 1,
            "model.compile_network": False,
        },
    )


PEER_VARIANTS = {
    "physicsnemo_hybrid": _peer(
        "PhysicsNeMo HybridMeshGraphNet (d = 32, 5 blocks)", "PhysicsNeMoHybrid",
        hidden_channels=32, processor_size=5,
    ),
    "physicsnemo_bsms": _peer(
        "PhysicsNeMo BiStrideMeshGraphNet (d = 32, 5 blocks, 2 pooled levels)", "PhysicsNeMoBSMS",
        hidden_channels=32, processor_size=5,
    ),
    "physicsnemo_hybrid_eq": _peer(
        "PhysicsNeMo HybridMeshGraphNet, AMPN's parameter count (d = 29, 5 blocks)", "PhysicsNeMoHybrid",
        hidden_channels=29, processor_size=5,
    ),
    "physicsnemo_bsms_eq": _peer(
        "PhysicsNeMo BiStrideMeshGraphNet, AMPN's parameter count (d = 27, 5 blocks)", "PhysicsNeMoBSMS",
        hidden_channels=27, processor_size=5,
    ),
}  # fmt: skip
DEFAULT_VARIANTS = list(VARIANTS)  # the peers need their own environment
VARIANTS.update(PEER_VARIANTS)
BASE_CONFIGS = {"coarse": "examples/configs/quickstart.yaml", "paper": "examples/configs/paper.yaml"}


# ---- configs ------------------------------------------------------------------------------------
def model_args(config: dict) -> dict:
    """A config's model arguments: ``model.init_args`` where the config names the class, else ``model``."""
    model = config.setdefault("model", {})
    return model.setdefault("init_args", {}) if "class_path" in model else model


def _set(config: dict, dotted: str, value: Any) -> None:
    section, key = dotted.split(".", 1)
    (model_args(config) if section == "model" else config.setdefault(section, {}))[key] = value


def validation_interval(steps: int, interval: int) -> int:
    """The largest divisor of ``steps`` that is at most ``interval``: validations end at the last step.

    ``best.ckpt`` is written at validations only, so a fit of 3,000 steps that validates every
    2,000 would be tested with its step-2,000 weights (the 3,000-step cells before 2026-12-07 were).
    """
    count = -(-steps // max(1, min(interval, steps)))  # validations: at least ceil(steps / interval)
    while steps % count:
        count += 1
    return steps // count


def cell_config(
    base: dict, changes: dict[str, Any], seed: int, steps: int, cell_dir: Path, args: argparse.Namespace
) -> dict:
    """The base config with ``changes`` (``section.key`` -> value), the seed, budget and folders.

    ``args`` gives the device, the dataset (``data_dir``), progress bars and the ``--set`` overrides.
    """
    config = copy.deepcopy(base)
    trainer = config.setdefault("trainer", {})
    config["seed_everything"] = seed
    trainer["max_steps"] = steps
    trainer["val_check_interval"] = validation_interval(steps, int(trainer.get("val_check_interval", steps)))
    trainer["accelerator"] = "gpu" if args.device == "cuda" else args.device
    trainer["default_root_dir"] = str(cell_dir)
    trainer["enable_progress_bar"] = args.progress
    trainer.pop("max_time", None)
    logger = trainer.get("logger")
    if isinstance(logger, dict):
        logger.setdefault("init_args", {})["save_dir"] = str(cell_dir)
    others = [c for c in trainer.get("callbacks") or [] if not c["class_path"].endswith("ModelCheckpoint")]
    trainer["callbacks"] = checkpoint_callbacks(cell_dir / "checkpoints") + others
    model_args(config).update(output_dir=str(cell_dir / "test"), rollout_seed=seed)
    config.setdefault("data", {})["data_dir"] = str(args.data_dir)
    for dotted, value in changes.items():
        _set(config, dotted, value)
    for dotted, value in args.set or []:
        _set(config, dotted, yaml.safe_load(value))
    return config


def checkpoint_callbacks(dirpath: Path) -> list[dict[str, Any]]:
    """The two checkpoints a cell relies on: ``best.ckpt`` (lowest validation rollout RMSE, tested)
    and ``last.ckpt`` (every validation, resumed from). Lightning >= 2.6 writes ``save_last``'s
    copy only when the monitored checkpoint improves, so ``last.ckpt`` is a checkpoint of its own."""
    common = {"dirpath": str(dirpath), "enable_version_counter": False}
    best = {**common, "filename": "best", "monitor": "val/rollout_rmse", "mode": "min"}
    last = {**common, "filename": "last"}
    return [
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint", "init_args": init_args}
        for init_args in (best, last)
    ]


def applicable(variant: str, base: dict) -> bool:
    """``k3`` only where the base config uses another k."""
    return variant != "k3" or model_args(copy.deepcopy(base)).get("contact_k", 3) != 3


# ---- one cell -------------------------------------------------------------------------------------
def _cli(stage: str, config_path: Path, log: Path, *extra: str) -> None:
    cmd = [sys.executable, "-m", "torch_ampn.cli.train", stage, "--config", str(config_path), *extra]
    with log.open("a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        done = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    if done.returncode != 0:
        raise RuntimeError(f"torch-ampn {stage} failed (exit {done.returncode}); see {log}")


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def simulator_reference(data_dir: Path, compile: bool = True, limit: int | None = None) -> dict[str, Any]:
    """The embedded simulator on the test trajectories: seconds per trajectory and its own repeatability.

    Compiled (its fastest settings; ``compile=False`` for quick checks), after a warm-up: one
    trajectory at a time and all at once, on the first ``limit`` test trajectories (all: None);
    ``fastest`` is the smaller time per trajectory. ``rmse_vs_dataset`` is the rollout RMSE
    (ply nodes, mean over steps and trajectories) of these new runs against the stored ones:
    the same settings simulated in another batch or thread count differ by that much, since
    the forming is chaotic (wrinkles); no surrogate can be expected to do better.
    """
    from torch_ampn.data import TrajectoryDataset
    from torch_ampn.rollout import rollout_rmse
    from torch_ampn.sim import StampFormingConfig, simulate_batch

    spec = json.loads((data_dir / "dataset.json").read_text())
    cfg = StampFormingConfig.from_dict(spec["simulator"])
    stored = list(TrajectoryDataset(data_dir, "test"))[:limit]
    seeds = [int(t.meta["seed"]) for t in stored]
    batches = len(seeds) > 1  # one test trajectory: "all at once" is "one at a time"
    if compile:  # compile outside the timings (each seed: its gripper layout may change the shapes)
        for seed in seeds:
            simulate_batch(cfg, [seed], compile=True)
        if batches:
            simulate_batch(cfg, seeds, compile=True)
    start = time.perf_counter()
    singles = [simulate_batch(cfg, [s], compile=compile)[0] for s in seeds]
    one_at_a_time = (time.perf_counter() - start) / len(seeds)
    together, batched = singles, one_at_a_time
    if batches:
        start = time.perf_counter()
        together = simulate_batch(cfg, seeds, compile=compile)
        batched = (time.perf_counter() - start) / len(seeds)

    def rmse(runs: list) -> float:
        values = [
            float(rollout_rmse(a.pos, b.pos, b.ply_mask)[1:].mean())
            for a, b in zip(runs, stored, strict=True)
        ]
        return sum(values) / len(values)

    return {
        "one_at_a_time": one_at_a_time,
        "batched": batched,
        "fastest": min(one_at_a_time, batched),
        "trajectories": len(seeds),
        "rmse_vs_dataset": {"one_at_a_time": rmse(singles), "batched": rmse(together)},
        "date": datetime.date.today().isoformat(),
        "machine": _machine(),
    }


def _simulator_of(args: argparse.Namespace) -> dict[str, Any]:
    """``simulator_reference`` of ``args.data_dir``, measured once per results folder and dataset:
    ``simulator.json`` is reused while the dataset (its ``dataset.json``) and the mode are the same."""
    import hashlib

    dataset = hashlib.sha256((args.data_dir / "dataset.json").read_bytes()).hexdigest()[:16]
    path = args.results / "simulator.json"
    if path.exists():
        stored = json.loads(path.read_text())
        same = (stored.get("dataset"), stored.get("mode"), stored.get("limit"))
        if same == (dataset, args.simulator_mode, args.simulator_trajectories):
            print("the embedded simulator: measured before (simulator.json)", flush=True)
            return stored
    print(f"the embedded simulator on the test trajectories ({args.simulator_mode}) ...", flush=True)
    simulator = simulator_reference(
        args.data_dir, compile=args.simulator_mode == "compiled", limit=args.simulator_trajectories
    )
    simulator.update(dataset=dataset, mode=args.simulator_mode, limit=args.simulator_trajectories)
    args.results.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, lambda p: p.write_text(json.dumps(simulator, indent=1)))
    return simulator


def _machine(device: str = "cpu") -> dict[str, Any]:
    return {
        "platform": platform.platform(),
        "processor": device_name("cpu"),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name() if device == "cuda" else None,
        "load_average": os.getloadavg(),
    }


def _contact_edges_per_step(module, trajectories: list, hierarchies) -> dict[str, float]:
    """Mean contact edges per step on the true test states: fine level and all levels together."""
    from torch_ampn.data import step_sample

    fine, total, count = 0, 0, 0
    for traj in trajectories:
        hierarchy = hierarchies(traj)
        for t in range(1, traj.num_steps + 1):
            data = module.surrogate.contact(step_sample(traj, t, hierarchy))
            sizes = [data.contact(k).edge_index.size(1) for k in range(module.surrogate.num_levels)]
            fine, total, count = fine + sizes[0], total + sum(sizes), count + 1
    return {"fine": fine / count, "all_levels": total / count}


def measure(cell_dir: Path, config: dict, args: argparse.Namespace) -> dict[str, Any]:
    """In-process measurements of a fitted and tested cell (see the module docstring)."""
    from torch_ampn.testing import count_parameters
    from torch_ampn.training import load_module
    from torch_ampn.training.datamodule import AMPNDataModule

    module = load_module(cell_dir / "checkpoints" / "best.ckpt", map_location="cpu")
    device = torch.device(args.device)
    module = module.to(device).eval()
    hp = module.hparams
    data = {k: v for k, v in config.get("data", {}).items() if k in ("min_coarse_nodes", "prior")}
    dm = AMPNDataModule(str(args.data_dir), generate=False, max_levels=hp.num_levels, **data)
    test = dm._rollout_split("test")
    items = [test[i] for i in range(len(test))]
    pred, _ = module.rollout_item(items[0])
    steps = [round(f * items[0].trajectory.num_steps) for f in STATE_FRACTIONS]
    trajectories = [item.trajectory for item in items]
    return {
        "states": {"trajectory": items[0].name, "steps": steps, "pos": pred[steps].clone()},
        "contact_edges_per_step": _contact_edges_per_step(module, trajectories, dm.hierarchies),
        "parameters": count_parameters(module.surrogate),
        "layers": module.surrogate.model.num_layers,
        # a peer applies each of its layers once; the AMPN's: layer_applications() of the config
        "layer_applications": getattr(module.surrogate.model, "layer_applications", None),
        "num_levels": hp.num_levels,
    }


def _relative(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    write(tmp)
    os.replace(tmp, path)


def fit_and_test(config: dict, cell_dir: Path) -> float:
    """``torch-ampn fit`` then ``test`` (best checkpoint) of ``config`` in ``cell_dir``; the fit's seconds.

    A fit of the same config that was stopped resumes from its ``last.ckpt``; one of another
    config starts over. Both log into ``cell_dir/log.txt``.
    """
    cell_dir.mkdir(parents=True, exist_ok=True)
    config_path = cell_dir / "config.yaml"
    last = cell_dir / "checkpoints" / "last.ckpt"
    if last.exists() and config_path.exists() and yaml.safe_load(config_path.read_text()) != config:
        shutil.rmtree(cell_dir / "checkpoints")  # another config: start over
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    log = cell_dir / "log.txt"
    start = time.perf_counter()
    _cli("fit", config_path, log, *(["--ckpt_path", str(last)] if last.exists() else []))
    fit_seconds = time.perf_counter() - start
    _cli("test", config_path, log, "--ckpt_path", str(cell_dir / "checkpoints" / "best.ckpt"))
    return fit_seconds


def run_cell(
    variant: str, seed: int, base: dict, args: argparse.Namespace, simulator: dict[str, Any]
) -> dict[str, Any]:
    """Fit, test and measure one cell; returns its result (also written atomically as JSON)."""
    cell_dir = args.workdir / f"{variant}_seed{seed}"
    config = cell_config(base, VARIANTS[variant].changes, seed, args.steps, cell_dir, args)
    fit_seconds = fit_and_test(config, cell_dir)
    test_dir = cell_dir / "test"
    summary = json.loads((test_dir / "test_summary.json").read_text())
    rows = _read_csv(test_dir / "test_rmse.csv")
    over_time = _read_csv(test_dir / "rmse_over_time.csv")
    measured = measure(cell_dir, config, args)
    states = measured.pop("states")
    result = {
        "variant": variant,
        "label": VARIANTS[variant].label,
        "seed": seed,
        "steps": args.steps,
        "resolution": args.resolution,
        "device": args.device,
        "data_dir": _relative(args.data_dir),
        "changes": VARIANTS[variant].changes,
        "base_changes": {k: yaml.safe_load(v) for k, v in args.set or []},  # --set, on every variant
        "rmse": summary["rollout_rmse"],
        "rmse_per_trajectory": {r["trajectory"]: float(r["model"]) for r in rows},
        "rollout_seconds": summary["rollout_seconds"],
        "baselines": {
            **{
                k: float(v) for k, v in summary.items() if k in ("static_rmse", "rigid_rmse", "baseline_rmse")
            },
            **{  # the setting-aware ones, with their R^2 of the setting effect
                f"{k}_rmse": sum(float(r[k]) for r in rows) / len(rows)
                for k in SETTING_BASELINES
                if k in rows[0]
            },
            **{f"{k}_r2": float(summary[f"{k}_r2"]) for k in SETTING_BASELINES if f"{k}_r2" in summary},
        },
        "setting_effect_r2": summary.get("setting_effect_r2"),
        "rmse_over_time": {k: [float(r[k]) for r in over_time] for k in over_time[0] if k != "step"},
        **measured,
        "simulator": simulator,
        "speedup": simulator["fastest"] / summary["rollout_seconds"],
        "fit_seconds": fit_seconds,
        "date": datetime.date.today().isoformat(),
        "machine": _machine(args.device),
    }
    args.results.mkdir(parents=True, exist_ok=True)
    _atomic_write(args.results / f"{variant}_seed{seed}.states.pt", lambda p: torch.save(states, p))
    # the fitted weights without optimizer state (small), for later side-by-side timings
    checkpoint = torch.load(cell_dir / "checkpoints" / "best.ckpt", map_location="cpu", weights_only=False)
    for key in ("optimizer_states", "lr_schedulers"):
        checkpoint.pop(key, None)
    _atomic_write(args.results / f"{variant}_seed{seed}.ckpt", lambda p: torch.save(checkpoint, p))
    _atomic_write(
        args.results / f"{variant}_seed{seed}.json", lambda p: p.write_text(json.dumps(result, indent=1))
    )
    return result


# ---- side-by-side timings -------------------------------------------------------------------------
def timings(args: argparse.Namespace, base: dict) -> dict[str, Any]:
    """Rollout time of every variant and the simulator's, side by side in one run (``--timings``).

    The cells' own rollout times come from whatever else ran on the machine during their
    test; this pass times one test trajectory per variant (the weights of its first seed
    with a saved ``.ckpt``) on the plain and the fast path, median of ``--repeats``, and the
    compiled simulator making the same trajectory, one after the other on an idle machine.
    Writes ``timings.json``; the report then takes its rollout and speed-up columns from it.
    """
    from torch_ampn.data import TrajectoryDataset
    from torch_ampn.sim import StampFormingConfig, simulate_batch
    from torch_ampn.training import load_module
    from torch_ampn.training.datamodule import AMPNDataModule

    spec = json.loads((args.data_dir / "dataset.json").read_text())
    cfg = StampFormingConfig.from_dict(spec["simulator"])
    traj = next(iter(TrajectoryDataset(args.data_dir, "test")))
    seed = int(traj.meta["seed"])
    compiled = args.simulator_mode == "compiled"
    if compiled:
        simulate_batch(cfg, [seed], compile=True)  # compile outside the timing
    sim = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        simulate_batch(cfg, [seed], compile=compiled)
        sim.append(time.perf_counter() - start)
    out: dict[str, Any] = {
        "trajectory": traj.meta.get("name", f"seed {seed}"),
        "simulator_seconds": statistics.median(sim),
        "variants": {},
        "date": datetime.date.today().isoformat(),
        "machine": _machine(args.device),
    }
    print(f"simulator: {out['simulator_seconds']:.2f} s", flush=True)
    for variant in [v for v in args.variants if applicable(v, base)]:
        ckpts = sorted(args.results.glob(f"{variant}_seed*.ckpt"))
        if not ckpts:
            continue
        module = load_module(ckpts[0], map_location=args.device).eval()
        hp = module.hparams
        prior = VARIANTS[variant].changes.get("data.prior")
        dm = AMPNDataModule(str(args.data_dir), generate=False, max_levels=hp.num_levels, prior=prior)
        item = dm._rollout_split("test")[0]
        from torch_ampn.rollout.fast import fast_path_supported

        no_fast = fast_path_supported(module.surrogate)  # e.g. plain-radius contact: the plain path
        entry: dict[str, Any] = {"checkpoint": ckpts[0].name, "fast_path": no_fast is None}
        for path in ("plain", "fast"):
            module.hparams.fast_rollout = path == "fast" and no_fast is None
            module.rollout_item(item)  # warm-up (and the fast path's compile)
            runs = [module.rollout_item(item)[1] for _ in range(args.repeats)]
            entry[f"{path}_seconds"] = statistics.median(runs)
            entry[f"{path}_speedup"] = out["simulator_seconds"] / entry[f"{path}_seconds"]
        out["variants"][variant] = entry
        print(
            f"{variant}: plain {entry['plain_seconds']:.2f} s, fast {entry['fast_seconds']:.2f} s "
            f"({entry['fast_speedup']:.1f}x the simulator)",
            flush=True,
        )
    _atomic_write(args.results / "timings.json", lambda p: p.write_text(json.dumps(out, indent=1)))
    return out


# ---- the report -------------------------------------------------------------------------------------
def _mean_std(values: list[float]) -> tuple[float, float]:
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return mean, std


def load_cells(results: Path) -> dict[tuple[str, int], dict]:
    cells = {}
    for path in sorted(results.glob("*_seed*.json")):
        cell = json.loads(path.read_text())
        cells[(cell["variant"], cell["seed"])] = cell
    return cells


def layer_applications(model: dict[str, Any], num_levels: int) -> int:
    """Message-passing layers applied per network call: the V-cycle runs Pre and Post on every level.

    ``model`` holds the stack sizes (the paper's 3, 2, 5, 3, 2 where absent).
    """
    size = {
        k: model.get(f"{k}_layers", d)
        for k, d in (("pre", 3), ("down", 2), ("solve", 5), ("post", 3), ("up", 2))
    }
    return (
        (size["pre"] + size["post"]) * num_levels
        + (size["down"] + size["up"]) * (num_levels - 1)
        + size["solve"]
    )


#: The setting-aware baselines of ``torch-ampn test`` (torch_ampn.baselines), with their labels.
SETTING_BASELINES = {
    "mean_trajectory": "the mean training trajectory, whatever the settings",
    "nearest_setting": "the training trajectory with the nearest settings",
    "linear_settings": "a linear regression on the settings",
    "pod_gp": "POD + Gaussian process on the settings",
}


def table(
    cells: dict[tuple[str, int], dict], variants: list[str], seeds: list[int], base: dict | None = None
) -> list[dict[str, Any]]:
    """One row per variant (mean and std over the seeds present), the simulator's repeatability,
    the trivial and the setting-aware baselines (from the test of a cell: the same test set)."""
    rows = []
    for variant in variants:
        done = [cells[(variant, s)] for s in seeds if (variant, s) in cells]
        row: dict[str, Any] = {
            "variant": variant,
            "label": VARIANTS[variant].label,
            "seeds": [c["seed"] for c in done],
        }
        row["missing_seeds"] = [s for s in seeds if (variant, s) not in cells]
        if done:
            for key, values in {
                "rmse": [c["rmse"] for c in done],
                "rollout_seconds": [c["rollout_seconds"] for c in done],
                "speedup": [c["speedup"] for c in done],
                "contact_edges": [c["contact_edges_per_step"]["fine"] for c in done],
                "contact_edges_all_levels": [c["contact_edges_per_step"]["all_levels"] for c in done],
            }.items():
                row[key], row[f"{key}_std"] = _mean_std(values)
            r2 = [c["setting_effect_r2"] for c in done if c.get("setting_effect_r2") is not None]
            if r2:
                row["r2"], row["r2_std"] = _mean_std(r2)
            row.update(layers=done[0]["layers"], parameters=done[0]["parameters"], steps=done[0]["steps"])
            row["layer_applications"] = done[0].get("layer_applications") or layer_applications(
                model_args(copy.deepcopy(base or {})), done[0]["num_levels"]
            )
            row["simulator_seconds"] = _mean_std([c["simulator"]["fastest"] for c in done])[0]
        rows.append(row)
    any_cell = next(iter(cells.values()), None)
    if any_cell is not None:
        floor = any_cell["simulator"]["rmse_vs_dataset"]["batched"]
        rows.append(
            {
                "variant": "simulator_rerun",
                "label": "the simulator run again (its repeatability)",
                "rmse": floor,
            }
        )
        for key, label in (
            ("static_rmse", "plies stay where they are"),
            ("rigid_rmse", "plies near the punch move with it"),
        ):
            if key in any_cell["baselines"]:
                rows.append(
                    {"variant": key.removesuffix("_rmse"), "label": label, "rmse": any_cell["baselines"][key]}
                )
        for key, label in SETTING_BASELINES.items():
            if f"{key}_rmse" in any_cell["baselines"]:
                found = any_cell["baselines"]
                rows.append(
                    {
                        "variant": key,
                        "label": label,
                        "rmse": found[f"{key}_rmse"],
                        "r2": found.get(f"{key}_r2"),
                    }
                )
    return rows


def markdown(rows: list[dict[str, Any]], seeds: list[int]) -> str:
    head = (
        "| model | RMSE [mm] | rollout [s] | speed-up vs simulator | contact edges / step (fine; all levels) "
        "| layers (applied per call) | parameters | seeds | R² of the setting effect |\n"
        "|---|---:|---:|---:|---:|---:|---:|---|---:|"
    )
    lines = [head]
    for r in rows:
        r2 = f"{r['r2']:.2f}" if r.get("r2") is not None else ""
        if "seeds" not in r:  # a baseline
            kind = "reference" if r["variant"] == "simulator_rerun" else "baseline"
            lines.append(f"| {r['label']} ({kind}) | {r['rmse']:.2f} | | | | | | | {r2} |")
        elif not r["seeds"]:
            lines.append(f"| {r['label']} | missing | | | | | | 0 of {len(seeds)} | |")
        else:
            missing = f" (missing {', '.join(map(str, r['missing_seeds']))})" if r["missing_seeds"] else ""
            mark = "" if r.get("timed") else "*"  # * : the cell's own test time (machine shared)
            lines.append(
                f"| {r['label']} | {r['rmse']:.2f} ± {r['rmse_std']:.2f} "
                f"| {r['rollout_seconds']:.2f}{mark} "
                f"| {r['speedup']:.1f}x{mark} "
                f"| {r['contact_edges']:,.0f}; {r['contact_edges_all_levels']:,.0f} "
                f"| {r['layers']} ({r['layer_applications']}) | {r['parameters']:,} "
                f"| {len(r['seeds'])}{missing} "
                + (f"| {r['r2']:.2f} ± {r['r2_std']:.2f} |" if "r2" in r else "| |")
            )
    if any("seeds" in r and r["seeds"] and not r.get("timed") for r in rows):
        lines.append("")
        lines.append(
            "\\* rollout time of the cell's own test, with other jobs on the machine; the others: "
            "`--timings`, every variant and the simulator side by side on one test trajectory."
        )
    return "\n".join(lines) + "\n"


def figures(
    cells: dict[tuple[str, int], dict], results: Path, out: Path, variants: list[str], seeds: list[int]
) -> list[Path]:
    """Fig. 2 and Fig. 3 of the paper for our data, and the RMSE over time of every variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_ampn.data import Trajectory
    from torch_ampn.viz import plot_laminate

    out.mkdir(parents=True, exist_ok=True)
    written = []
    fig, ax = plt.subplots(figsize=(8, 4.8))
    colors = [c for i, c in enumerate(plt.get_cmap("tab10").colors) if i != 7]  # grey: the baselines'
    for i, variant in enumerate(variants):
        curves = [
            torch.tensor(cells[(variant, s)]["rmse_over_time"]["model"])
            for s in seeds
            if (variant, s) in cells
        ]
        if curves:
            color = colors[i % len(colors)]
            ax.plot(torch.stack(curves).mean(0), label=VARIANTS[variant].label, lw=1.6, color=color)
    any_cell = next(iter(cells.values()), None)
    if any_cell is not None:
        curves = any_cell["rmse_over_time"]
        rigid = [name for name in curves if name.startswith("rigid_r")]
        best = min(rigid, key=lambda name: sum(curves[name][1:])) if rigid else None  # as the table's
        labels = {"static": "baseline: plies stay where they are"}
        if best is not None:
            radius = best.removeprefix("rigid_r")
            labels[best] = f"baseline: plies within {radius} mm of the punch move with it"
        for name, style in (("static", ":"), (best, "--")):
            if name is not None:
                ax.plot(curves[name], ls=style, color="0.35", lw=1, label=labels[name])
    ax.set(
        xlabel="step",
        ylabel="RMSE over ply nodes [mm]",
        yscale="log",
        title="Rollout error over time (mean over seeds)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    written.append(out / "compare_rmse_over_time.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    seed = next((s for s in seeds if ("ampn", s) in cells), None)
    if seed is None:
        return written
    states = {
        v: torch.load(results / f"{v}_seed{seed}.states.pt", weights_only=True)
        for v in variants
        if (v, seed) in cells
    }
    name = states["ampn"]["trajectory"]
    data_dir = ROOT / any_cell["data_dir"]  # absolute paths stay absolute
    truth = Trajectory.load(data_dir / "test" / f"{name}.pt")
    panels = {"fig2": (["ampn"], (0.7, 1.0)), "fig3": (["ampn", "robin5", "robin10", "robin20"], (0.9, 1.0))}
    for fig_name, (models, fractions) in panels.items():
        models = [m for m in models if m in states]
        columns = [*models, "truth"]
        fig = plt.figure(figsize=(4.2 * len(columns), 3.6 * len(fractions)))
        u3 = truth.pos[:, :, 2] - truth.pos[0, :, 2]
        vmin = float(u3[:, truth.ply_mask].min())
        for i, fraction in enumerate(fractions):
            step = round(fraction * truth.num_steps)
            for j, column in enumerate(columns):
                if column == "truth":
                    pos = truth.pos[step]
                else:
                    s = states[column]
                    pos = s["pos"][s["steps"].index(step)]
                ax = fig.add_subplot(len(fractions), len(columns), i * len(columns) + j + 1, projection="3d")
                last = plot_laminate(
                    ax, pos, truth.cells, truth.node_type, pos[:, 2] - truth.pos[0, :, 2], vmin, 0.0
                )
                ax.view_init(elev=28, azim=-62)
                label = "truth (simulator)" if column == "truth" else VARIANTS[column].label
                ax.set_title(f"{label}, {fraction:.0%}", fontsize=9)
        fig.subplots_adjust(right=0.88)
        fig.colorbar(last, cax=fig.add_axes((0.91, 0.25, 0.015, 0.5)), label="e3 displacement [mm]")
        fig.suptitle(f"Unseen test trajectory {name} (seed {seed})")
        written.append(out / f"compare_{fig_name}.png")
        fig.savefig(written[-1], dpi=90)
        plt.close(fig)
    return written


def report(args: argparse.Namespace, base: dict) -> dict[str, Any]:
    variants = [v for v in args.variants if applicable(v, base)]
    found = {variant for variant, _ in load_cells(args.results)}
    # every variant with cells in the folder gets its row, so that a run of a few variants (the
    # peers' job, say) does not write a table without the others
    variants += [v for v in VARIANTS if v in found and v not in variants and applicable(v, base)]
    cells = {k: c for k, c in load_cells(args.results).items() if k[0] in variants and k[1] in args.seeds}
    rows = table(cells, variants, args.seeds, base)
    timed = args.results / "timings.json"
    if timed.exists():  # side-by-side rollout times replace the cells' own
        measured = json.loads(timed.read_text())
        for row in rows:
            entry = measured["variants"].get(row["variant"])
            if entry is not None and row.get("seeds"):
                row["rollout_seconds"], row["speedup"] = entry["fast_seconds"], entry["fast_speedup"]
                row["plain_rollout_seconds"] = entry["plain_seconds"]
                row["timed"] = measured["date"]
    text = markdown(rows, args.seeds)
    print(text)
    args.results.mkdir(parents=True, exist_ok=True)
    _atomic_write(args.results / "table.md", lambda p: p.write_text(text))
    meta = {"steps": args.steps, "resolution": args.resolution, "seeds": args.seeds, "rows": rows}
    _atomic_write(args.results / "table.json", lambda p: p.write_text(json.dumps(meta, indent=1)))
    if cells and not args.no_figures:
        for path in figures(
            cells, args.results, args.figures or args.results / "figures", variants, args.seeds
        ):
            print(f"wrote {path}")
    return meta


# ---- command line -----------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, choices=list(VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument(
        "--steps", type=int, default=None, help="training steps per fit (default: the base config's)"
    )
    parser.add_argument("--resolution", choices=list(BASE_CONFIGS), default="coarse")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("--config", type=Path, default=None, help="base config (default: by --resolution)")
    parser.add_argument(
        "--data-dir", type=Path, default=None, help="dataset (default: the config's data_dir)"
    )
    parser.add_argument("--results", type=Path, default=None, help="cell JSONs and the table")
    parser.add_argument("--workdir", type=Path, default=None, help="checkpoints and logs of the cells")
    parser.add_argument(
        "--figures", type=Path, default=None, help="figure folder (default: <results>/figures)"
    )
    parser.add_argument(
        "--set", nargs=2, action="append", metavar=("KEY", "VALUE"), help="change the base config"
    )
    parser.add_argument("--simulator-mode", choices=["compiled", "eager"], default="compiled")
    parser.add_argument(
        "--simulator-trajectories",
        type=int,
        default=None,
        help="time the simulator on the first N test trajectories (default: all)",
    )
    parser.add_argument("--report", action="store_true", help="only build the table and figures")
    parser.add_argument(
        "--timings", action="store_true", help="time every variant's rollout and the simulator side by side"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per path with --timings")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--progress", action="store_true", help="show the fits' progress bars")
    args = parser.parse_args(argv)
    suffix = "" if args.resolution == "coarse" else f"_{args.resolution}"
    args.config = args.config or ROOT / BASE_CONFIGS[args.resolution]
    args.results = args.results or ROOT / f"benchmarks/results/compare{suffix}"
    args.workdir = args.workdir or ROOT / f"outputs/compare{suffix}"
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    base = yaml.safe_load(args.config.read_text())
    args.data_dir = (args.data_dir or ROOT / base.get("data", {}).get("data_dir", "data/default")).resolve()
    args.steps = args.steps or int(base.get("trainer", {}).get("max_steps", 3000))
    if args.timings:
        timings(args, base)
        report(args, base)
        return 0
    if args.report:
        report(args, base)
        return 0
    if not (args.data_dir / "dataset.json").exists():  # the base config's dataset, made once
        from torch_ampn.sim import generate_dataset

        data = base.get("data", {})
        counts = (data.get("num_train", 24), data.get("num_val", 2), data.get("num_test", 4))
        generate_dataset(args.data_dir, *counts, resolution=data.get("resolution", "coarse"))
    todo = [(v, s) for v in args.variants if applicable(v, base) for s in args.seeds]
    done = [(v, s) for v, s in todo if (args.results / f"{v}_seed{s}.json").exists()]
    todo = [cell for cell in todo if cell not in done]
    if done:
        print(f"{len(done)} cells done before, skipped: {', '.join(f'{v}_seed{s}' for v, s in done)}")
    simulator = None
    if todo:
        simulator = _simulator_of(args)
        print(
            f"simulator: {simulator['fastest']:.2f} s per trajectory; its own repeatability "
            f"{simulator['rmse_vs_dataset']['batched']:.3f} mm",
            flush=True,
        )
    failed: list[str] = []
    for i, (variant, seed) in enumerate(todo, 1):
        print(
            f"[{i}/{len(todo)}] {variant} seed {seed}: fit ({args.steps} steps), test, measure ...",
            flush=True,
        )
        try:
            cell = run_cell(variant, seed, base, args, simulator)
        except RuntimeError as err:  # a failed fit or test: the other cells still run
            failed.append(f"{variant}_seed{seed}")
            print(f"[{i}/{len(todo)}] {variant} seed {seed}: FAILED, no result written ({err})", flush=True)
            continue
        print(
            f"[{i}/{len(todo)}] {variant} seed {seed}: RMSE {cell['rmse']:.3f} mm, rollout "
            f"{cell['rollout_seconds']:.2f} s, {cell['speedup']:.1f}x the simulator, "
            f"fit {cell['fit_seconds']:.0f} s",
            flush=True,
        )
    report(args, base)
    if failed:
        print(f"{len(failed)} cell(s) failed: {', '.join(failed)}; their logs are in {args.workdir}")
    return 1 if failed else 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
