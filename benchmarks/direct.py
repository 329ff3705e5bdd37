"""The direct model on unseen settings: direct AMPN, direct flat network, against POD + GP and the rest.

    python benchmarks/direct.py data/v3_400 --variants direct_ampn direct_flat --sizes 400 \
        --seeds 0 --steps 2000 --out benchmarks/results/direct

Every run is ``torch-ampn fit`` then ``torch-ampn test`` of ``examples/configs/direct.yaml``
(the variant's network, ``--steps`` optimiser steps) on the first ``n`` training trajectories of
the dataset (a folder of links per size) and its whole test split, so the test report's
setting-aware baselines (mean trajectory, nearest setting, linear, POD + GP) are fitted on the
same ``n`` trajectories. ``--set key=value`` changes the config's ``model`` settings
(``data.key=value`` the data module's, e.g. ``data.prior=pod_gp`` with ``base=prior``) for every
variant and ``--tag`` names such a run (``<variant>-<tag>``). ``direct_flat`` is the one-level
network with the width that gives it the AMPN's parameter count (within 3 %). Runs already done
(``<out>/runs/<variant>_n<n>_s<seed>_t<steps>.json``) are kept, so a stopped benchmark resumes.
Writes ``<out>/table.json`` (per variant, size and step count: the RMSE's mean and std over
seeds, the seeds, R^2 of the setting effect, seconds per prediction, the baselines) and prints
the table.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import statistics
import time
from pathlib import Path

import yaml

from torch_ampn.utils.io import atomic_write_text

CONFIG = Path(__file__).resolve().parents[1] / "examples" / "configs" / "direct.yaml"
BASELINES = ("mean_trajectory", "nearest_setting", "linear_settings", "pod_gp")
VARIANTS = ("direct_ampn", "direct_flat")


def subset(data_dir: Path, n: int, root: Path) -> Path:
    """A dataset folder whose train split is links to the first ``n`` training files of ``data_dir``."""
    files = sorted((data_dir / "train").glob("*.pt"))
    if n > len(files):
        raise ValueError(f"{data_dir / 'train'}: {len(files)} trajectories, fewer than --sizes {n}")
    out = root / f"{data_dir.name}_n{n}"
    (out / "train").mkdir(parents=True, exist_ok=True)
    for f in files[:n]:
        link = out / "train" / f.name
        if not link.exists():
            link.symlink_to(f.resolve())
    for split in ("val", "test"):
        if not (out / split).exists():
            (out / split).symlink_to((data_dir / split).resolve())
    if (data_dir / "dataset.json").exists() and not (out / "dataset.json").exists():
        (out / "dataset.json").symlink_to((data_dir / "dataset.json").resolve())
    return out


def number(value: object) -> object:
    """A YAML value, with a string such as ``3e-3`` (a string to YAML 1.1) read as a float."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def parameters(model: dict) -> int:
    """Parameters of the direct model of these ``model`` settings."""
    from torch_ampn.training import DirectLightningModule

    return sum(p.numel() for p in DirectLightningModule(**model).surrogate.parameters())


def variant_model(name: str, base: dict) -> dict:
    """The ``model`` settings of a variant: the config's (direct AMPN) or the flat one at equal parameters."""
    if name == "direct_ampn":
        return dict(base)
    target = parameters(base)
    best = None
    for width in range(8, 4 * int(base["hidden_channels"]) + 1, 2):
        flat = {**base, "num_levels": 1, "hidden_channels": width, "mlp_channels": width}
        gap = abs(parameters(flat) - target) / target
        if best is None or gap < best[0]:
            best = (gap, flat)
    assert best is not None and best[0] < 0.03, best
    return best[1]


def run_name(variant: str, tag: str) -> str:
    """A run's variant name: ``<variant>-<tag>``, or the variant for the config as it is."""
    return f"{variant}-{tag}" if tag else variant


def run(
    data_dir: Path,
    variant: str,
    seed: int,
    steps: int,
    work: Path,
    changes: dict | None = None,
    tag: str = "",
) -> dict:
    """Fit and test one run (``changes``: ``model`` settings over the config's, ``data.*`` the data
    module's); returns its record."""
    from torch_ampn.cli.train import main

    config = yaml.safe_load(CONFIG.read_text())
    changes = changes or {}
    data_changes = {k.removeprefix("data."): v for k, v in changes.items() if k.startswith("data.")}
    model_changes = {k: v for k, v in changes.items() if not k.startswith("data.")}
    model = variant_model(variant, {**config["model"]["init_args"], **model_changes})
    name = run_name(variant, tag)
    out = work / f"{name}_{data_dir.name}_s{seed}_t{steps}"
    config["seed_everything"] = seed
    config["trainer"].update(
        max_steps=steps, val_check_interval=max(steps // 4, 1), default_root_dir=str(out),
        enable_progress_bar=False,
    )  # fmt: skip
    config["trainer"]["logger"]["init_args"]["save_dir"] = str(out)
    for callback in config["trainer"]["callbacks"]:
        if "dirpath" in callback.get("init_args", {}):
            callback["init_args"]["dirpath"] = str(out / "checkpoints")
    config["model"]["init_args"] = {**model, "output_dir": str(out / "report"), "export_xdmf": False}
    config["data"].update(data_dir=str(data_dir), generate=False, **data_changes)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    start = time.perf_counter()
    main(["fit", "--config", str(path)])
    fit_seconds = time.perf_counter() - start
    main(["test", "--config", str(path), "--ckpt_path", str(out / "checkpoints" / "best.ckpt")])
    summary = json.loads((out / "report" / "test_summary.json").read_text())
    with open(out / "report" / "test_rmse.csv") as f:
        rows = list(csv.DictReader(f))
    return {
        "variant": name,
        "changes": changes or {},
        "train": len(list((data_dir / "train").glob("*.pt"))),
        "test": len(rows),
        "seed": seed,
        "steps": steps,
        "parameters": parameters(model),
        "model": {k: model[k] for k in ("num_levels", "hidden_channels", "mlp_channels")},
        "rmse_mm": float(summary["rollout_rmse"]),
        "setting_effect_r2": float(summary["setting_effect_r2"]),
        "seconds_per_prediction": float(summary["rollout_seconds"]),
        "fit_seconds": fit_seconds,
        "baselines_rmse_mm": {
            b: statistics.fmean(float(r[b]) for r in rows) for b in BASELINES if b in rows[0]
        },
        "baselines_r2": {b: float(summary[f"{b}_r2"]) for b in BASELINES if f"{b}_r2" in summary},
    }


def table(records: list[dict]) -> list[dict]:
    """Per (variant, train size, steps): mean and std over seeds."""
    groups: dict[tuple[str, int, int], list[dict]] = {}
    for r in records:
        groups.setdefault((r["variant"], r["train"], r["steps"]), []).append(r)
    rows = []
    for (variant, n, steps), rs in sorted(groups.items(), key=lambda kv: (kv[0][1], kv[0][2], kv[0][0])):
        rmse = [r["rmse_mm"] for r in rs]
        rows.append({
            "variant": variant,
            "train": n,
            "steps": steps,
            "seeds": [r["seed"] for r in rs],
            "rmse_mm_mean": statistics.fmean(rmse),
            "rmse_mm_std": statistics.pstdev(rmse),
            "setting_effect_r2_mean": statistics.fmean(r["setting_effect_r2"] for r in rs),
            "seconds_per_prediction": statistics.fmean(r["seconds_per_prediction"] for r in rs),
            "parameters": rs[0]["parameters"],
            "baselines_rmse_mm": rs[0]["baselines_rmse_mm"],
            "baselines_r2": rs[0]["baselines_r2"],
        })  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--sizes", nargs="+", type=int, default=[400])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE",
        help="model settings over the config's (YAML); data.KEY=VALUE: the data module's",
    )  # fmt: skip
    parser.add_argument("--tag", default="", help="name of the changed runs (required with --set)")
    parser.add_argument("--work", type=Path, default=Path("outputs/direct_runs"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/direct"))
    args = parser.parse_args()
    changes = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--set {item}: expected KEY=VALUE")
        changes[key] = number(yaml.safe_load(value))
    if changes and not args.tag:
        parser.error("--set needs --tag (the runs' name)")
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    for n in args.sizes:
        data = subset(args.data_dir, n, args.work / "data")
        for variant in args.variants:
            for seed in args.seeds:
                done = args.out / "runs" / f"{run_name(variant, args.tag)}_n{n}_s{seed}_t{args.steps}.json"
                if done.exists():
                    continue
                record = run(data, variant, seed, args.steps, args.work, changes, args.tag)
                record["date"] = datetime.date.today().isoformat()
                record["data"] = str(args.data_dir)
                atomic_write_text(done, json.dumps(record, indent=2))
    records = [json.loads(p.read_text()) for p in sorted((args.out / "runs").glob("*.json"))]
    rows = table(records)
    result = {
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/direct.py " + " ".join(os.sys.argv[1:]),
        "rows": rows,
    }
    atomic_write_text(args.out / "table.json", json.dumps(result, indent=2))
    head = f"{'variant':<24}{'train':>6}{'steps':>7}{'seeds':>7}{'RMSE mm':>10}{'std':>8}{'R2':>7}"
    head += f"{'s/pred':>8}"
    print(f"{head}  baselines (mm)")
    for r in rows:
        base = " ".join(f"{k}={v:.3f}" for k, v in r["baselines_rmse_mm"].items())
        print(
            f"{r['variant']:<24}{r['train']:>6}{r['steps']:>7}{len(r['seeds']):>7}{r['rmse_mm_mean']:>10.4f}"
            f"{r['rmse_mm_std']:>8.4f}{r['setting_effect_r2_mean']:>7.3f}"
            f"{r['seconds_per_prediction']:>8.3f}  {base}"
        )


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()
    main()
