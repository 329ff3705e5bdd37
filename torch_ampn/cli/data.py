"""``torch-ampn-data``: make the default dataset with the embedded simulator, convert and export.

    torch-ampn-data generate --out data/default --num-train 32 --num-val 4 --num-test 4
    torch-ampn-data generate --out data/paper --resolution paper --num-train 684 --shard 3/16  # job 3 of 16
    torch-ampn-data generate --out data/paper --resolution paper --device cuda --batch 32    # on a GPU
    torch-ampn-data generate --out data/family --family default    # every trajectory its own part
    torch-ampn-data generate --out data/soft --simulator '{"shear_stiffness": 2.0}'   # other settings
    torch-ampn-data check data/default
    torch-ampn-data spread data/default --split test --chaos 12   # do the settings decide the part?
    torch-ampn-data energy data/default --plot outputs/energy.png   # kinetic, strain, dissipated, work
    torch-ampn-data convert results.xdmf --out data/mine/train/run_000.pt
    torch-ampn-data convert run_001/d3plot --parts parts.yaml --out data/mine/train/run_001.pt   # LS-DYNA
    torch-ampn-data convert run_002.inp --parts parts.yaml --out data/mine/train/run_002.pt      # Abaqus
    torch-ampn-data export data/default/test/traj_200000.pt --out outputs/traj.xdmf
    torch-ampn-data export data/default/test/traj_200000.pt --out outputs/run --format d3plot

``generate`` runs :func:`torch_ampn.sim.generate_dataset` (dataset layout and seeds: see
:mod:`torch_ampn.sim.dataset`); ``spread`` measures how far the settings move the plies
against the forming's chaos floor (:mod:`torch_ampn.sim.spread`).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError
from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.dataset import generate_dataset
from torch_ampn.sim.family import PartFamily


def _shard(text: str) -> tuple[int, int]:
    """``"I/N"`` -> ``(I, N)``."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (e.g. 0/4), got {text!r}") from None
    return index, count


def _check(root: Path) -> int:
    """Print the summary of :func:`~torch_ampn.data.check_dataset`; 1 if there are problems."""
    from torch_ampn.data.dataset import check_dataset

    rows, problems = check_dataset(root)
    print(f"{'split':<6} {'files':>6} {'meshes':>7}  nodes  steps")
    for r in rows:
        print(f"{r['split']:<6} {r['files']:>6} {r['topologies']:>7}  {r['nodes']}  {r['steps']}")
    for line in problems:
        print(f"problem: {line}", file=sys.stderr)
    print(f"{root}: {'OK' if not problems else f'{len(problems)} problem(s)'}")
    return 1 if problems else 0


def _spread(root: Path, split: str, chaos: int, perturbation: float, out: Path | None) -> int:
    """Print (and write as JSON) the setting spread of ``root/split`` against its chaos floor."""
    from torch_ampn.data.dataset import split_files
    from torch_ampn.sim.spread import (
        chaos_floor,
        format_reliability,
        format_report,
        rerun_perturbed,
        setting_spread,
        spread_report,
        two_run_reliability,
    )

    files = split_files(root, split)
    if len(files) < 2:
        raise ValueError(f"{root / split}: the spread needs at least 2 trajectories, found {len(files)}")
    trajectories = [Trajectory.load(f) for f in files]
    spread = setting_spread(trajectories)
    print(f"chaos floor: simulating {chaos} trajectories again from a perturbed start ...", flush=True)
    again = rerun_perturbed(trajectories[:chaos], perturbation)
    report = spread_report(spread, chaos_floor(trajectories[:chaos], perturbation, again=again))
    report.update(dataset=str(root), split=split)
    print(format_report(report))
    if chaos >= 3:  # the two runs' ranks of the settings by part quality
        report["reliability"] = two_run_reliability(trajectories[:chaos], again)
        print(format_reliability(report["reliability"]))
    else:
        print("two-run reliability of the part-quality measures: needs --chaos 3 or more")
    if out is not None:
        from torch_ampn.utils.io import atomic_write_text

        atomic_write_text(out, json.dumps(report, indent=1))
        print(f"wrote {out}")
    return 0


def _energy(path: Path, split: str, plot: Path | None, out: Path | None, curves: int) -> int:
    """Print the energy balance of a trajectory file or a dataset split; plot and write it on request."""
    from torch_ampn.sim.energy import energy_summary, plot_energy

    if path.is_dir():
        from torch_ampn.data.dataset import split_files

        files = split_files(path, split)
    else:
        files = [path]
    if not files:
        raise ValueError(f"{path / split}: no trajectories")
    rows, records = [], []
    for f in files:
        traj = Trajectory.load(f)
        record = traj.meta.get("energy")
        if record is None:
            raise ValueError(
                f"{f}: field 'meta' has no 'energy' (not made by the embedded simulator, or made "
                "before it kept its energy balance: simulate it again)"
            )
        rows.append((f.name, energy_summary(record, str(f))))
        records.append((f.stem, record, traj.time.tolist()))
    print(
        f"{'trajectory':<22} {'KE/IE':>6} {'QS %':>5} {'damp/W':>7} {'visc/W':>7} {'fric/W':>7} "
        f"{'W [J]':>7} {'grip [J]':>8} {'peak KE [J]':>11} {'balance':>8}"
    )
    for name, r in rows:
        print(
            f"{name:<22} {r['kinetic_over_internal']:6.3f} {100 * r['quasi_static_fraction']:5.0f} "
            f"{r['damping_over_work']:7.3f} {r['viscosity_over_work']:7.3f} {r['friction_over_work']:7.3f} "
            f"{r['final']['external'] / 1000:7.2f} {r['final']['work_grippers'] / 1000:8.3f} "
            f"{r['peak_kinetic'] / 1000:11.3f} {r['balance_error']:8.3f}"
        )
    print(
        "KE/IE: median kinetic over internal energy (quasi-static: <= 0.05); QS %: steps at or below "
        "it; damp/W, visc/W, fric/W: the mass damping's, the viscosity's and friction's dissipation "
        "over the external work W (grippers + punch); balance: largest |ETOTAL| over W"
    )
    if plot is not None:
        shown = records[:curves]
        print(f"wrote {plot_energy([(n, r) for n, r, _ in shown], plot, times=shown[0][2])}")
    if out is not None:
        from torch_ampn.utils.io import atomic_write_text

        atomic_write_text(out, json.dumps({name: r for name, r in rows}, indent=1))
        print(f"wrote {out}")
    return 0


def _family(spec: str | None) -> PartFamily | None:
    """``None``, the default family, or the family of a YAML/JSON file (``ValueError`` naming the file)."""
    if spec is None:
        return None
    if spec == "default":
        return PartFamily()
    path = Path(spec)
    if not path.is_file():
        raise FileNotFoundError(f"--family {spec}: no such file (or 'default')")
    try:
        if path.suffix == ".json":
            values = json.loads(path.read_text())
        else:
            import yaml  # PyYAML comes with the train extra

            values = yaml.safe_load(path.read_text())
        return PartFamily.from_dict(values or {})
    except ImportError as err:
        raise ValueError(f"{path}: reading YAML needs PyYAML (pip install pyyaml); or give JSON") from err
    except Exception as err:  # noqa: BLE001 - a parse or settings error: one line naming the file
        raise ValueError(f"{path}: not a family of parts ({' '.join(str(err).split())})") from err


def _simulator(spec: str | None, resolution: str) -> StampFormingConfig | None:
    """``None``, or the resolution's settings overridden by a YAML/JSON file or inline JSON."""
    if spec is None:
        return None
    base = StampFormingConfig.paper() if resolution == "paper" else StampFormingConfig()
    path = Path(spec)
    where = f"--simulator {spec}"
    try:
        if path.is_file():
            where = str(path)
            import yaml  # PyYAML comes with the train extra; JSON is YAML

            values = yaml.safe_load(path.read_text())
        else:
            values = json.loads(spec)
        config = StampFormingConfig.from_dict(values or {}, base=base)
        config.validate()
    except ImportError as err:
        raise ValueError(f"{where}: reading a file needs PyYAML (pip install pyyaml); or give JSON") from err
    except Exception as err:  # noqa: BLE001 - a parse or settings error: one line naming the source
        raise ValueError(f"{where}: not simulator settings ({' '.join(str(err).split())})") from err
    return config


def _device(name: str) -> str:
    """``name`` if torch can run there, else ``ValueError`` with the reason."""
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"--device: {err}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine")
    return name


def _convert(path: Path, parts: Path | None, displacements: Path | None = None) -> Trajectory:
    """The trajectory of a solver's output.

    A d3plot (a file named ``d3plot*``, or a folder holding ``d3plot``), an Abaqus deck with its
    displacement table, or a meshio time series.
    """
    d3plot = path / "d3plot" if path.is_dir() and (path / "d3plot").is_file() else path
    if path.suffix.lower() == ".inp":
        from torch_ampn.data.abaqus_io import read_abaqus

        return read_abaqus(path, displacements, parts)
    if displacements is not None:
        raise ValueError(f"--displacements is for Abaqus .inp input; {path} is not one")
    if d3plot.name.startswith("d3plot"):
        from torch_ampn.data.d3plot_io import read_d3plot

        return read_d3plot(d3plot, parts)
    if parts is not None:
        raise ValueError(f"--parts is for d3plot and .inp input; {path} is neither")
    from torch_ampn.data.meshio_io import read_time_series

    return read_time_series(path)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``torch-ampn-data``."""
    parser = argparse.ArgumentParser(prog="torch-ampn-data", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="simulate a dataset with the embedded simulator (resumable)")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--num-train", type=int, default=32)
    g.add_argument("--num-val", type=int, default=4)
    g.add_argument("--num-test", type=int, default=4)
    g.add_argument("--resolution", choices=["coarse", "paper"], default="coarse")
    g.add_argument("--workers", type=int, default=None, help="processes (default: CPU cores; 1 on a GPU)")
    g.add_argument("--batch", type=int, default=4, help="trajectories simulated together per process")
    g.add_argument("--no-compile", action="store_true", help="do not torch.compile the solver step")
    g.add_argument("--device", default="cpu", help="where the solver runs, e.g. cuda (default: cpu)")
    g.add_argument(
        "--family",
        default=None,
        metavar="FILE|default",
        help="a family of parts: every trajectory its own tool geometry and ply stack, sampled from the "
        "ranges of a YAML/JSON file of PartFamily settings, or 'default' (torch_ampn.sim.family)",
    )
    g.add_argument(
        "--simulator",
        default=None,
        metavar="FILE|JSON",
        help="simulator settings that override the resolution's (StampFormingConfig fields), as a "
        "YAML/JSON file or inline JSON, e.g. '{\"shear_stiffness\": 2.0}'",
    )
    g.add_argument(
        "--shard", type=_shard, default=None, metavar="I/N", help="make only part I of N (0 <= I < N)"
    )
    k = sub.add_parser("check", help="load every trajectory of a dataset folder and summarise it")
    k.add_argument("root", type=Path)
    s = sub.add_parser("spread", help="how far the settings move the plies, against the chaos floor")
    s.add_argument("root", type=Path)
    s.add_argument("--split", default="train")
    s.add_argument("--chaos", type=int, default=2, help="trajectories simulated again (default 2)")
    s.add_argument("--perturbation", type=float, default=1e-6, help="initial ply displacement, mm")
    s.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    n = sub.add_parser("energy", help="the simulator's energy balance of a trajectory or a dataset split")
    n.add_argument("path", type=Path, help="a trajectory .pt or a dataset folder")
    n.add_argument("--split", default="train", help="the split of a dataset folder (default train)")
    n.add_argument("--plot", type=Path, default=None, help="plot the terms and ratios over time (PNG)")
    n.add_argument("--curves", type=int, default=3, help="trajectories in the plot (default 3)")
    n.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    c = sub.add_parser(
        "convert",
        help="LS-DYNA d3plot, Abaqus .inp + ODB table, or meshio series (.xdmf, .vtu folder) -> .pt",
    )
    c.add_argument(
        "input", type=Path, help="run/d3plot, an Abaqus .inp, a .xdmf file or a folder of .vtu files"
    )
    c.add_argument("--out", type=Path, required=True)
    c.add_argument(
        "--parts", type=Path, default=None, help="d3plot, .inp: the part map (default: parts.yaml beside it)"
    )
    c.add_argument(
        "--displacements",
        type=Path,
        default=None,
        help=".inp: the table of scripts/abaqus_odb_export.py (default: the deck's name with .npz)",
    )
    e = sub.add_parser("export", help="trajectory .pt -> XDMF time series for ParaView, or a d3plot")
    e.add_argument("input", type=Path)
    e.add_argument("--out", type=Path, required=True, help="a .xdmf file, or a folder with --format d3plot")
    e.add_argument("--format", choices=["xdmf", "d3plot"], default="xdmf")
    args = parser.parse_args(argv)
    try:
        if args.command == "generate":
            paths = generate_dataset(
                args.out,
                args.num_train,
                args.num_val,
                args.num_test,
                args.resolution,
                args.workers,
                args.batch,
                compile=not args.no_compile,
                device=_device(args.device),
                family=_family(args.family),
                config=_simulator(args.simulator, args.resolution),
                **({"shard": args.shard} if args.shard else {}),
            )
            print(f"{len(paths)} trajectories in {args.out}")
        elif args.command == "check":
            return _check(args.root)
        elif args.command == "spread":
            if args.chaos < 1:
                raise ValueError(f"--chaos must be >= 1, got {args.chaos}")
            return _spread(args.root, args.split, args.chaos, args.perturbation, args.json)
        elif args.command == "energy":
            return _energy(args.path, args.split, args.plot, args.json, args.curves)
        elif args.command == "convert":
            traj = _convert(args.input, args.parts, args.displacements)
            traj.save(args.out)
            print(
                f"wrote {args.out}: {traj.num_nodes} nodes, {traj.num_steps} steps, "
                f"{traj.num_components} components, {traj.num_grippers} grippers"
            )
        elif args.format == "d3plot":
            from torch_ampn.data.d3plot_io import write_d3plot

            print(f"wrote {write_d3plot(Trajectory.load(args.input), args.out)} (and its parts.yaml)")
        else:
            from torch_ampn.data.meshio_io import export_xdmf

            print(f"wrote {export_xdmf(Trajectory.load(args.input), args.out)}")
    except (TrajectoryFormatError, FileNotFoundError, ValueError, ImportError) as err:
        print(f"torch-ampn-data: error: {err}", file=sys.stderr)
        return 2
    return 0


def entry_point() -> None:
    """Console script ``torch-ampn-data``: :func:`main` with the CPU tuning of a program of its own."""
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()
    raise SystemExit(main())


if __name__ == "__main__":
    entry_point()
