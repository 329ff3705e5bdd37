"""``torch-ampn-data``: make the default dataset with the embedded simulator, convert and export.

    torch-ampn-data generate --out data/default --num-train 32 --num-val 4 --num-test 4
    torch-ampn-data convert results.xdmf --out data/mine/train/run_000.pt
    torch-ampn-data export data/default/test/traj_200000.pt --out outputs/traj.xdmf

Dataset layout: ``<out>/{train,val,test}/traj_<seed>.pt`` (see
:mod:`torch_ampn.data.trajectory` for the file format) and ``<out>/dataset.json`` with the
simulator settings. Seeds: train ``0..``, val ``100000..``, test ``200000..``, so that
adding trajectories to one split never changes another.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError
from torch_ampn.sim.config import StampFormingConfig

SPLIT_SEED_OFFSET = {"train": 0, "val": 100_000, "test": 200_000}


def trajectory_path(root: Path, split: str, seed: int) -> Path:
    """Where the trajectory of ``seed`` in ``split`` lives."""
    return root / split / f"traj_{seed:06d}.pt"


def _is_valid(path: Path) -> bool:
    try:
        Trajectory.load(path)
    except (OSError, TrajectoryFormatError):
        return False
    return True


def _simulate_chunk(args: tuple[dict, list[tuple[str, int]], str, bool]) -> list[str]:
    """Worker: simulate a chunk of (split, seed) jobs together and save each trajectory."""
    from torch_ampn.sim import simulate_batch

    cfg_dict, jobs, root, compile_ = args
    torch.set_num_threads(1)
    cfg = StampFormingConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg_dict.items()})
    trajs = simulate_batch(cfg, [seed for _, seed in jobs], compile=compile_)
    out = []
    for (split, seed), traj in zip(jobs, trajs, strict=True):
        path = trajectory_path(Path(root), split, seed)
        traj.save(path)
        out.append(str(path))
    return out


def generate(
    out: Path,
    num_train: int,
    num_val: int,
    num_test: int,
    resolution: str = "coarse",
    workers: int | None = None,
    batch: int = 4,
    compile: bool = True,
    progress: bool = True,
    config: StampFormingConfig | None = None,
) -> list[Path]:
    """Simulate the missing trajectories of a dataset (existing valid files are kept).

    Args:
        out: Dataset folder.
        num_train: Trajectories in the train split (seeds ``0 ..``).
        num_val: Trajectories in the val split (seeds ``100000 ..``).
        num_test: Trajectories in the test split (seeds ``200000 ..``).
        resolution: ``"coarse"`` (default settings) or ``"paper"`` (3,200 triangles per ply).
        workers: Processes (default: CPU cores).
        batch: Trajectories simulated together in one process.
        compile: ``torch.compile`` the solver step.
        progress: Show a progress bar.
        config: Explicit simulator settings (overrides ``resolution``).

    Returns:
        The paths of all trajectories of the dataset.
    """
    if resolution not in ("coarse", "paper"):
        raise ValueError(f"resolution must be 'coarse' or 'paper', got {resolution!r}")
    cfg = config or (StampFormingConfig.paper() if resolution == "paper" else StampFormingConfig())
    out.mkdir(parents=True, exist_ok=True)
    spec_path = out / "dataset.json"
    spec = json.loads(json.dumps(dict(resolution=resolution, simulator=cfg.to_dict())))
    if spec_path.exists():
        old = json.loads(spec_path.read_text())
        if old.get("simulator") != spec["simulator"]:
            raise ValueError(f"{spec_path}: the folder holds a dataset made with other simulator settings")
    tmp = spec_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(spec, indent=2))
    os.replace(tmp, spec_path)

    wanted = [
        (split, SPLIT_SEED_OFFSET[split] + i)
        for split, count in (("train", num_train), ("val", num_val), ("test", num_test))
        for i in range(count)
    ]
    todo = [(s, seed) for s, seed in wanted if not _is_valid(trajectory_path(out, s, seed))]
    chunks = [todo[i : i + batch] for i in range(0, len(todo), batch)]
    workers = max(1, min(workers or os.cpu_count() or 1, len(chunks) or 1))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="generate", unit="traj")
        bar.write(f"{len(wanted) - len(todo)} of {len(wanted)} trajectories exist; simulating {len(todo)}")
    jobs = [(cfg.to_dict(), chunk, str(out), compile) for chunk in chunks]
    if workers == 1:
        results = map(_simulate_chunk, jobs)
        for done in results:
            bar and bar.update(len(done))
    elif jobs:
        with mp.get_context("spawn").Pool(workers) as pool:
            for done in pool.imap_unordered(_simulate_chunk, jobs):
                bar and bar.update(len(done))
    if bar is not None:
        bar.close()
    return [trajectory_path(out, s, seed) for s, seed in wanted]


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
    g.add_argument("--workers", type=int, default=None, help="processes (default: CPU cores)")
    g.add_argument("--batch", type=int, default=4, help="trajectories simulated together per process")
    g.add_argument("--no-compile", action="store_true", help="do not torch.compile the solver step")
    c = sub.add_parser("convert", help="meshio time series (.xdmf or folder of .vtu) -> trajectory .pt")
    c.add_argument("input", type=Path)
    c.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("export", help="trajectory .pt -> XDMF time series for ParaView")
    e.add_argument("input", type=Path)
    e.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        if args.command == "generate":
            paths = generate(
                args.out,
                args.num_train,
                args.num_val,
                args.num_test,
                args.resolution,
                args.workers,
                args.batch,
                compile=not args.no_compile,
            )
            print(f"{len(paths)} trajectories in {args.out}")
        elif args.command == "convert":
            from torch_ampn.data.meshio_io import read_time_series

            traj = read_time_series(args.input)
            traj.save(args.out)
            print(f"wrote {args.out}: {traj.num_nodes} nodes, {traj.num_steps} steps")
        else:
            from torch_ampn.data.meshio_io import export_xdmf

            print(f"wrote {export_xdmf(Trajectory.load(args.input), args.out)}")
    except (TrajectoryFormatError, FileNotFoundError, ValueError) as err:
        print(f"torch-ampn-data: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
