"""One model for a family of parts against a single-part model with the same budget, in one run.

Two cells, each ``torch-ampn fit`` then ``test`` in subprocesses, with the same recipe,
network, seed and number of training steps (``--steps``, not a time limit):

    single   the single-part quickstart (``examples/configs/quickstart.yaml``) on its own
             dataset (one part: the default double dome and [0/45/90/-45] stack), tested on
             unseen process settings of that part
    family   ``examples/configs/family.yaml`` on a family dataset (every trajectory its own
             part: ``torch_ampn.sim.PartFamily``'s ranges), tested on parts the training split
             never saw: inside the ranges (``inside``) and outside them, one dataset per
             ``--extrapolation NAME=JSON`` (default: ``deeper``, domes 55-65 mm deep where
             training has 40-55; ``angle30``, plies at +-30 deg where training has 0/45/90/-45;
             ``box``, a box-section punch, a tool shape the family never draws);
             and on ``--num-seen`` of its own training trajectories (``seen``: parts and
             settings it was trained on), which tells underfitting from a generalisation gap

The datasets are made by the embedded simulator when missing. Each cell writes
``<results>/<cell>_seed<k>.json`` atomically when it is complete; a rerun skips finished cells
and a stopped fit resumes from its ``last.ckpt``. The report (printed, ``table.md``,
``table.json``) gives each test set's rollout RMSE next to its best trivial baseline and
against the single-part model, one row per test part, and a figure of the best and worst
test parts inside and outside the ranges (final shape, predicted vs true).

    python benchmarks/family.py                                  # data, both fits, tests, report
    python benchmarks/family.py --steps 6000 --num-train 48
    python benchmarks/family.py --cells single                  # one cell; the other later
    python benchmarks/family.py --report
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare import (  # noqa: E402 - the comparison's cell machinery
    _atomic_write,
    _cli,
    _machine,
    _read_csv,
    _relative,
    cell_config,
    fit_and_test,
)

ROOT = Path(__file__).resolve().parents[1]
EXTRAPOLATIONS = {
    "deeper": {"dome_depth": [55.0, 65.0]},
    "angle30": {"ply_angles": [30.0, -30.0]},
    "box": {"shapes": ["box"]},
}
SET_LABELS = {
    "single": "single-part model, its own part (unseen settings)",
    "inside": "family model, unseen parts inside the ranges",
    "seen": "family model, its own training parts (seen in training)",
}
#: Test-set names that an ``--extrapolation`` may not take.
RESERVED_SETS = ("single", "inside", "seen")


def _set_label(name: str, family: dict | None = None) -> str:
    if name in SET_LABELS:
        return SET_LABELS[name]
    what = ", ".join(f"{k} {v}" for k, v in (family or {}).items())
    return f"family model, {name} ({what})" if what else f"family model, {name}"


# ---- data -----------------------------------------------------------------------------------------
def make_datasets(args: argparse.Namespace, single: dict, family: dict) -> None:
    """Simulate whatever the runs need and is missing (existing trajectories are kept).

    Through the data module of each config, so that the data are what ``torch-ampn fit``
    would make (its ``data.simulator`` and ``data.family`` settings).
    """
    from torch_ampn.sim import PartFamily
    from torch_ampn.training.datamodule import AMPNDataModule

    def prepare(data: dict, **changes: Any) -> None:
        AMPNDataModule(**{**data, **changes, "generate": True}).prepare_data()

    data = single.get("data", {})
    print(f"single-part data {_relative(args.single_data)}", flush=True)
    prepare(data, data_dir=str(args.single_data))
    data = family.get("data", {})
    spec = data.get("family") or "default"
    base = PartFamily() if spec == "default" else PartFamily.from_dict(spec)
    print(
        f"family data {_relative(args.family_data)}: {args.num_train} / {args.num_val} / {args.num_test}",
        flush=True,
    )
    counts = dict(num_train=args.num_train, num_val=args.num_val, num_test=args.num_test)
    prepare(data, data_dir=str(args.family_data), **counts)
    if args.num_seen > 0:
        make_seen_dataset(args.family_data, _seen_dir(args), args.num_seen)
    for name, changes in args.extrapolation.items():
        print(f"extrapolation data {name}: {args.num_extrapolation} test parts, {changes}", flush=True)
        prepare(
            data,
            data_dir=str(_extrapolation_dir(args, name)),
            num_train=0,
            num_val=0,
            num_test=args.num_extrapolation,
            family={**base.to_dict(), **changes},
        )


def make_seen_dataset(family_data: Path, seen_data: Path, count: int) -> list[Path]:
    """A dataset folder whose ``test`` split is copies of the first ``count`` training trajectories.

    Testing the family model on it gives its error on parts (and process settings) it was
    trained on. Files are copied under a temporary name and renamed, so a stopped run leaves
    no half-written trajectory; existing copies are kept.

    Returns:
        The test files of ``seen_data``.
    """
    from torch_ampn.data.dataset import split_files

    train = split_files(family_data, "train")[:count]
    if len(train) < count:
        raise ValueError(f"{family_data}: --num-seen {count} but only {len(train)} training trajectories")
    (seen_data / "test").mkdir(parents=True, exist_ok=True)
    spec = family_data / "dataset.json"
    if spec.exists():
        _atomic_write(seen_data / "dataset.json", lambda p: shutil.copyfile(spec, p))
    out = []
    for src in train:
        dst = seen_data / "test" / src.name
        if not dst.exists():
            _atomic_write(dst, lambda p, src=src: shutil.copyfile(src, p))
        out.append(dst)
    return out


def _extrapolation_dir(args: argparse.Namespace, name: str) -> Path:
    return args.family_data.with_name(f"{args.family_data.name}_{name}")


def _seen_dir(args: argparse.Namespace) -> Path:
    return _extrapolation_dir(args, "seen")


def _cell_result(args: argparse.Namespace, name: str) -> Path:
    """The JSON a cell's fit and tests end in; its presence means the cell is done."""
    return args.results / f"{name}_seed{args.seed}.json"


def _test_on(cell_dir: Path, data_dir: Path, count: int, out: Path) -> None:
    """``torch-ampn test`` of a cell's best checkpoint on the ``count`` test trajectories of ``data_dir``."""
    _cli(
        "test",
        cell_dir / "config.yaml",
        cell_dir / "log.txt",
        "--ckpt_path", str(cell_dir / "checkpoints" / "best.ckpt"),
        "--data.data_dir", str(data_dir),
        "--data.num_train", "0", "--data.num_val", "0",
        "--data.num_test", str(count),
        "--model.check_mesh", "false",
        "--model.output_dir", str(out),
    )  # fmt: skip


# ---- cells ----------------------------------------------------------------------------------------
def _test_set(test_dir: Path) -> dict[str, Any]:
    """A ``torch-ampn test`` folder as a result: summary and one row per trajectory."""
    summary = json.loads((test_dir / "test_summary.json").read_text())
    rows = _read_csv(test_dir / "test_rmse.csv")
    baselines = [k for k in rows[0] if k not in ("trajectory", "part", "model", "rollout_seconds")]
    return {
        "rmse": summary["rollout_rmse"],
        "baseline_rmse": summary["baseline_rmse"],
        "static_rmse": summary["static_rmse"],
        "rollout_seconds": summary["rollout_seconds"],
        "trajectories": [
            {
                "trajectory": r["trajectory"],
                "part": r.get("part", ""),
                "model": float(r["model"]),
                "best_baseline": min(float(r[k]) for k in baselines),
            }
            for r in rows
        ],
    }


def run_cell(name: str, args: argparse.Namespace, base: dict) -> dict[str, Any]:
    """Fit and test one cell (``single`` or ``family``); the family cell also tests every extrapolation."""
    cell_dir = args.workdir / f"{name}_seed{args.seed}"
    cell_args = argparse.Namespace(**vars(args))
    cell_args.data_dir = args.single_data if name == "single" else args.family_data
    changes: dict[str, Any] = {"data.generate": False}
    if name == "family":
        changes.update(
            {"data.num_train": args.num_train, "data.num_val": args.num_val, "data.num_test": args.num_test}
        )
    config = cell_config(base, changes, args.seed, args.steps, cell_dir, cell_args)
    fit_seconds = fit_and_test(config, cell_dir)
    sets = {"single" if name == "single" else "inside": _test_set(cell_dir / "test")}
    if name == "family":
        if args.num_seen > 0:
            _test_on(cell_dir, _seen_dir(args), args.num_seen, cell_dir / "test_seen")
            sets["seen"] = _test_set(cell_dir / "test_seen")
        for set_name in args.extrapolation:
            out = cell_dir / f"test_{set_name}"
            _test_on(cell_dir, _extrapolation_dir(args, set_name), args.num_extrapolation, out)
            sets[set_name] = {**_test_set(out), "family_changes": args.extrapolation[set_name]}
    result = {
        "cell": name,
        "seed": args.seed,
        "steps": args.steps,
        "config": _relative(args.family_config if name == "family" else args.single_config),
        "data_dir": _relative(cell_args.data_dir),
        "num_train": config["data"].get("num_train"),
        "sets": sets,
        "fit_seconds": fit_seconds,
        "checkpoint": _relative(cell_dir / "checkpoints" / "best.ckpt"),
        "date": datetime.date.today().isoformat(),
        "machine": _machine(args.device),
    }
    args.results.mkdir(parents=True, exist_ok=True)
    _atomic_write(_cell_result(args, name), lambda p: p.write_text(json.dumps(result, indent=1)))
    return result


# ---- the report -------------------------------------------------------------------------------------
def table(cells: dict[str, dict]) -> list[dict[str, Any]]:
    """One row per test set: model and best-baseline RMSE (means over its parts) and the ratios."""
    single = cells.get("single", {}).get("sets", {}).get("single")
    rows = []
    for cell in ("single", "family"):
        for set_name, s in cells.get(cell, {}).get("sets", {}).items():
            row = {
                "set": set_name,
                "label": _set_label(set_name, s.get("family_changes")),
                "parts": len(s["trajectories"]),
                "rmse": s["rmse"],
                "baseline_rmse": s["baseline_rmse"],
                "below_baseline": s["baseline_rmse"] / s["rmse"],
            }
            if single is not None:
                row["vs_single"] = s["rmse"] / single["rmse"]
            rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]], cells: dict[str, dict]) -> str:
    lines = [
        "| test set | parts | RMSE [mm] | best trivial baseline [mm] | below the baseline "
        "| vs single-part model |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        vs = f"{r['vs_single']:.2f}x" if "vs_single" in r else "(missing)"
        lines.append(
            f"| {r['label']} | {r['parts']} | {r['rmse']:.2f} | {r['baseline_rmse']:.2f} "
            f"| {r['below_baseline']:.1f}x | {vs} |"
        )
    family = cells.get("family")
    if family is not None:
        lines += [
            "",
            "| test set | trajectory | part | RMSE [mm] | best baseline [mm] |",
            "|---|---|---|---:|---:|",
        ]
        for set_name, s in family["sets"].items():
            for t in s["trajectories"]:
                lines.append(
                    f"| {set_name} | {t['trajectory']} | {t['part']} | {t['model']:.2f} "
                    f"| {t['best_baseline']:.2f} |"
                )
    return "\n".join(lines) + "\n"


def best_and_worst(family: dict) -> list[tuple[str, dict]]:
    """The best and the worst test part inside the ranges and outside them (by RMSE / best baseline).

    Training parts (the ``seen`` set) are in neither group.
    """
    picked = []
    for group in (["inside"], [s for s in family["sets"] if s not in RESERVED_SETS]):
        parts = [(s, t) for s in group if s in family["sets"] for t in family["sets"][s]["trajectories"]]
        if parts:
            score = lambda st: st[1]["model"] / st[1]["best_baseline"]  # noqa: E731
            picked += [min(parts, key=score), max(parts, key=score)]
    return picked


def figure(family: dict, args: argparse.Namespace, path: Path) -> Path:
    """Final shape of the best and worst test parts, predicted vs true (rolled out again here)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_ampn.training import load_module
    from torch_ampn.training.datamodule import AMPNDataModule
    from torch_ampn.viz import plot_laminate

    module = load_module(ROOT / family["checkpoint"], map_location="cpu").eval()
    cases = best_and_worst(family)
    fig = plt.figure(figsize=(10, 3.4 * len(cases)))
    fig.subplots_adjust(left=0.0, right=0.88, bottom=0.02, top=0.96, hspace=0.25, wspace=0.0)
    for i, (set_name, entry) in enumerate(cases):
        data_dir = args.family_data if set_name == "inside" else _extrapolation_dir(args, set_name)
        dm = AMPNDataModule(str(data_dir), generate=False, max_levels=module.hparams.num_levels)
        split = dm._rollout_split("test")
        item = next(split[j] for j in range(len(split)) if split[j].name == entry["trajectory"])
        pred, _ = module.rollout_item(item)
        traj = item.trajectory
        u3 = {"predicted": pred[-1, :, 2] - traj.pos[0, :, 2], "true": traj.pos[-1, :, 2] - traj.pos[0, :, 2]}
        vmin = float(min(u[traj.ply_mask].min() for u in u3.values()))
        kind = "best" if i % 2 == 0 else "worst"
        for j, (label, pos) in enumerate((("predicted", pred[-1]), ("true", traj.pos[-1]))):
            ax = fig.add_subplot(len(cases), 2, 2 * i + j + 1, projection="3d")
            box = ax.get_position()
            last = plot_laminate(
                ax, pos, traj.cells, traj.node_type, u3[label], vmin, 0.0, show_tools=False, components=[0]
            )
            ax.view_init(elev=28, azim=-62)
            ax.set_title(
                f"{kind} of {set_name}: {entry['part']}\n{label}, bottom ply; RMSE {entry['model']:.2f} mm "
                f"(baseline {entry['best_baseline']:.2f})",
                fontsize=8,
            )
        # the row's own colour bar, right of its two panels
        cax = fig.add_axes((0.9, box.y0 + 0.15 * box.height, 0.012, 0.7 * box.height))
        fig.colorbar(last, cax=cax, label="e3 displacement [mm]")
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, lambda p: fig.savefig(p, dpi=80, format="png"))
    plt.close(fig)
    return path


def report(args: argparse.Namespace) -> dict[str, Any]:
    cells = {}
    for name in ("single", "family"):
        path = _cell_result(args, name)
        if path.exists():
            cells[name] = json.loads(path.read_text())
    rows = table(cells)
    text = markdown(rows, cells)
    missing = [n for n in ("single", "family") if n not in cells]
    if missing:
        text += f"\nmissing cells: {', '.join(missing)}\n"
    print(text)
    args.results.mkdir(parents=True, exist_ok=True)
    _atomic_write(args.results / "table.md", lambda p: p.write_text(text))
    meta = {
        "seed": args.seed,
        "steps": {n: c["steps"] for n, c in cells.items()},
        "num_train": {n: c["num_train"] for n, c in cells.items()},
        "rows": rows,
        "missing": missing,
    }
    _atomic_write(args.results / "table.json", lambda p: p.write_text(json.dumps(meta, indent=1)))
    if "family" in cells and not args.no_figures:
        print(f"wrote {figure(cells['family'], args, args.results / 'best_and_worst.png')}")
    return meta


# ---- command line -----------------------------------------------------------------------------------
def _extrapolation(text: str) -> tuple[str, dict]:
    name, _, spec = text.partition("=")
    try:
        changes = yaml.safe_load(spec)
    except yaml.YAMLError as err:
        raise argparse.ArgumentTypeError(f"--extrapolation {text}: not NAME=JSON ({err})") from err
    if not name or not isinstance(changes, dict):
        raise argparse.ArgumentTypeError(f"--extrapolation {text}: not NAME=JSON with a mapping")
    if name in RESERVED_SETS:
        raise argparse.ArgumentTypeError(
            f"--extrapolation {text}: the name {name!r} is taken (reserved: {', '.join(RESERVED_SETS)})"
        )
    return name, changes


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--seed", type=int, default=0)
    add("--steps", type=int, default=None, help="steps of both fits (default: the family config's)")
    add("--single-config", type=Path, default=ROOT / "examples/configs/quickstart.yaml")
    add("--family-config", type=Path, default=ROOT / "examples/configs/family.yaml")
    add("--single-data", type=Path, default=None, help="default: the single config's data_dir")
    add("--family-data", type=Path, default=None, help="default: the family config's data_dir")
    add("--num-train", type=int, default=None, help="family training parts (default: the config's)")
    add("--num-val", type=int, default=None)
    add("--num-test", type=int, default=None, help="unseen parts inside the ranges")
    add(
        "--extrapolation", type=_extrapolation, action="append", metavar="NAME=JSON",
        help="a test set outside the ranges: family settings that change (default: deeper, angle30)",
    )  # fmt: skip
    add("--num-extrapolation", type=int, default=4, help="test parts per extrapolation set")
    add(
        "--num-seen", type=int, default=8,
        help="training trajectories the family model is also tested on (0: none)",
    )  # fmt: skip
    add("--device", choices=["cpu", "cuda"], default="cpu")
    add("--results", type=Path, default=ROOT / "benchmarks/results/family")
    add("--workdir", type=Path, default=ROOT / "outputs/family_bench")
    add("--set", nargs=2, action="append", metavar=("KEY", "VALUE"), help="change both configs")
    add(
        "--cells", nargs="+", choices=["single", "family"], default=["single", "family"],
        help="fit and test only these cells (the report needs both)",
    )  # fmt: skip
    add("--report", action="store_true", help="only build the table and the figure")
    add("--no-figures", action="store_true")
    add("--progress", action="store_true", help="show the fits' progress bars")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configs = {
        "single": yaml.safe_load(args.single_config.read_text()),
        "family": yaml.safe_load(args.family_config.read_text()),
    }
    fam_data = configs["family"].get("data", {})
    args.single_data = (args.single_data or ROOT / configs["single"]["data"]["data_dir"]).resolve()
    args.family_data = (args.family_data or ROOT / fam_data["data_dir"]).resolve()
    args.num_train = fam_data.get("num_train", 48) if args.num_train is None else args.num_train
    args.num_val = fam_data.get("num_val", 4) if args.num_val is None else args.num_val
    args.num_test = fam_data.get("num_test", 8) if args.num_test is None else args.num_test
    args.extrapolation = dict(args.extrapolation) if args.extrapolation else dict(EXTRAPOLATIONS)
    args.steps = args.steps or int(configs["family"].get("trainer", {}).get("max_steps", 3000))
    if args.report:
        report(args)
        return 0
    make_datasets(args, configs["single"], configs["family"])
    names = [name for name in ("single", "family") if name in args.cells]
    for i, name in enumerate(names, 1):
        tag = f"[{i}/{len(names)}] {name}"
        if _cell_result(args, name).exists():
            print(f"{tag}: done before, skipped", flush=True)
            continue
        print(f"{tag}: fit ({args.steps} steps), test ...", flush=True)
        cell = run_cell(name, args, configs[name])
        summary = ", ".join(f"{s} {v['rmse']:.3f} mm" for s, v in cell["sets"].items())
        print(f"{tag}: {summary}; fit {cell['fit_seconds']:.0f} s", flush=True)
    if all(_cell_result(args, name).exists() for name in ("single", "family")):
        report(args)
    else:
        print("report: waits for both cells (run the other with --cells, then --report)", flush=True)
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
