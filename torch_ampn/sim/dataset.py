"""Datasets made with the embedded simulator: resumable, parallel generation of the split folders.

Layout: ``<out>/{train,val,test}/traj_<seed>.pt`` (see :mod:`torch_ampn.data.trajectory` for
the file format) and ``<out>/dataset.json`` with the simulator settings. Seeds: train ``0..``,
val ``100000..``, test ``200000..``, so that adding trajectories to one split never changes
another.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError
from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.family import PartFamily, part_config, sample_part
from torch_ampn.sim.simulate import simulate_batch
from torch_ampn.sim.spread import blow_up
from torch_ampn.utils.io import atomic_write_text

if TYPE_CHECKING:
    from tqdm import tqdm

SPLIT_SEED_OFFSET = {"train": 0, "val": 100_000, "test": 200_000}
#: Subfolder of a split where blown-up runs are set aside (:func:`torch_ampn.sim.spread.blow_up`).
FAILED = "failed"


def trajectory_path(root: Path, split: str, seed: int) -> Path:
    """Where the trajectory of ``seed`` in ``split`` lives."""
    return root / split / f"traj_{seed:06d}.pt"


def failed_path(root: Path, split: str, seed: int) -> Path:
    """Where a blown-up trajectory of ``seed`` in ``split`` is set aside (not part of the split)."""
    return root / split / FAILED / f"traj_{seed:06d}.pt"


def _is_done(root: Path, split: str, seed: int) -> bool:
    """``seed`` was simulated: its trajectory is in the split, or set aside as blown up.

    A trajectory in the split that is blown up (a dataset made before the check) is set aside.
    """
    path = trajectory_path(root, split, seed)
    try:
        traj = Trajectory.load(path)
    except (OSError, TrajectoryFormatError):
        return _is_valid(failed_path(root, split, seed))
    reason = blow_up(traj)
    if reason is not None:
        _set_aside(traj, root, split, seed, reason)
        path.unlink()
    return True


def _set_aside(traj: Trajectory, root: Path, split: str, seed: int, reason: str) -> Path:
    """Write a blown-up ``traj`` to ``<split>/failed/`` with ``reason`` (a design study drops failed runs)."""
    traj.meta["failed"] = reason
    path = failed_path(root, split, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    traj.save(path)
    return path


def _is_valid(path: Path) -> bool:
    try:
        Trajectory.load(path)
    except (OSError, TrajectoryFormatError):
        return False
    return True


def _simulate_chunk(args: tuple) -> list[str]:
    """Worker: simulate a chunk of (split, seed) jobs together and save the trajectories asked for.

    ``args``: ``(config dict, jobs, which to write, root, compile, device[, part])``; a
    family's chunk is one job, whose ``part`` goes into the trajectory's ``meta["part"]``.
    """
    cfg_dict, jobs, write, root, compile_, device, *part = args
    # one thread, in a worker process and in the caller's alike: a reduction's summation order,
    # and so a trajectory's last bits, then do not depend on the worker count, the shard or the cores
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = StampFormingConfig.from_dict(cfg_dict)
        trajs = simulate_batch(cfg, [seed for _, seed in jobs], compile=compile_, device=device)
    finally:
        torch.set_num_threads(threads)
    out = []
    for (split, seed), traj, wanted in zip(jobs, trajs, write, strict=True):
        if part and part[0] is not None:
            traj.meta["part"] = dict(part[0])
        if wanted:
            reason = blow_up(traj)
            if reason is None:
                path = trajectory_path(Path(root), split, seed)
                traj.save(path)
            else:
                path = _set_aside(traj, Path(root), split, seed, reason)
            out.append(str(path))
    return out


def _run_in_processes(jobs: list[tuple], workers: int, bar: tqdm | None) -> None:
    """Simulate ``jobs`` in ``workers`` spawned processes; a worker that dies is an error, not a hang.

    Spawned workers re-import the caller's ``__main__``: a script that calls
    :func:`generate_dataset` at top level (no ``if __name__ == "__main__":``) makes every worker
    start the generation again, which multiprocessing refuses, so the worker dies.
    """
    try:
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            for future in as_completed([pool.submit(_simulate_chunk, job) for job in jobs]):
                done = future.result()
                bar and bar.update(len(done))
    except BrokenProcessPool as err:
        raise RuntimeError(
            "generate_dataset: a worker process died (killed, out of memory, or the calling script "
            'has no `if __name__ == "__main__":` guard around the generation; spawned workers '
            "re-import it); the files written so far are kept, rerun to complete them, or pass workers=1"
        ) from err


def generate_dataset(
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
    shard: tuple[int, int] | None = None,
    device: torch.device | str = "cpu",
    family: PartFamily | None = None,
) -> list[Path]:
    """Simulate the missing trajectories of a dataset (existing valid files are kept).

    The trajectories are simulated in fixed chunks of ``batch`` consecutive (split, seed)
    jobs, the same for every run of the same split sizes, so that a trajectory is always
    simulated in the same batch (with ``compile`` its last bits depend on the batch), and every
    chunk is simulated on one thread (its last bits would depend on the thread count too). With
    ``shard=(i, n)`` only chunks ``i, i + n, i + 2n, ...`` are simulated: ``n`` jobs with
    ``i = 0 .. n-1``, in any order, on any machines sharing the folder (or copied together
    afterwards), make the same files as one job. Rerunning a job completes what it left.

    Args:
        out: Dataset folder.
        num_train: Trajectories in the train split (seeds ``0 ..``).
        num_val: Trajectories in the val split (seeds ``100000 ..``).
        num_test: Trajectories in the test split (seeds ``200000 ..``).
        resolution: ``"coarse"`` (default settings) or ``"paper"`` (3,200 triangles per ply).
        workers: Processes (default: CPU cores; one on a GPU).
        batch: Trajectories simulated together in one process (on a GPU: as many as fit).
        compile: ``torch.compile`` the solver step.
        progress: Show a progress bar.
        config: Explicit simulator settings (overrides ``resolution``).
        shard: ``(i, n)``: make only the ``i``-th of ``n`` disjoint parts (``0 <= i < n``).
        device: Where the solver runs (``"cuda"``: on a GPU); the trajectories' last bits
            depend on it, as they do on the batch.
        family: A family of parts (:mod:`torch_ampn.sim.family`): every trajectory gets the
            part :func:`~torch_ampn.sim.family.sample_part` draws for its seed, on top of
            ``config`` (or ``resolution``), simulated alone (its own mesh), its part in
            ``meta["part"]``; ``dataset.json`` records the family.

    A run that blows up (:func:`~torch_ampn.sim.spread.blow_up`) is written to
    ``<split>/failed/`` with the reason in ``meta["failed"]``, outside the split, and not
    simulated again: the split holds one trajectory fewer.

    Returns:
        The paths of the trajectories of the dataset (of the shard's part with ``shard``),
        without the runs set aside.

    Raises:
        ValueError: For an unknown ``resolution``, or a folder whose ``dataset.json`` holds
            other simulator settings.
        RuntimeError: When a worker process dies (a script that calls this with more than
            one worker needs an ``if __name__ == "__main__":`` guard).
    """
    if resolution not in ("coarse", "paper"):
        raise ValueError(f"resolution must be 'coarse' or 'paper', got {resolution!r}")
    index, count = shard or (0, 1)
    if not 0 <= index < count:
        raise ValueError(f"shard must be i/n with 0 <= i < n, got {index}/{count}")
    cfg = config or (StampFormingConfig.paper() if resolution == "paper" else StampFormingConfig())
    out.mkdir(parents=True, exist_ok=True)
    spec_path = out / "dataset.json"
    spec = dict(resolution=resolution, simulator=cfg.to_dict())
    if family is not None:
        family.validate()
        spec["family"] = family.to_dict()
    spec = json.loads(json.dumps(spec))
    old = json.loads(spec_path.read_text()) if spec_path.exists() else None
    made_with = (spec["simulator"], spec.get("family"))
    if old is not None and (old.get("simulator"), old.get("family")) != made_with:
        what = "simulator settings" if old.get("simulator") != spec["simulator"] else "family of parts"
        raise ValueError(f"{spec_path}: the folder holds a dataset made with another {what}")
    if old != spec:  # written once: processes that share a complete folder only read it
        atomic_write_text(spec_path, json.dumps(spec, indent=2))

    wanted = [
        (split, SPLIT_SEED_OFFSET[split] + i)
        for split, count in (("train", num_train), ("val", num_val), ("test", num_test))
        for i in range(count)
    ]
    if family is not None:
        batch = 1  # every trajectory its own part, so its own mesh
    chunks = [wanted[i : i + batch] for i in range(0, len(wanted), batch)][index::count]
    wanted = [job for chunk in chunks for job in chunk]
    # a chunk with a missing trajectory is simulated whole (its batch is its batch); only the
    # missing files are written
    missing = {job for job in wanted if not _is_done(out, *job)}
    chunks = [chunk for chunk in chunks if missing.intersection(chunk)]
    todo = [job for job in wanted if job in missing]
    device = str(device)
    if workers is None and torch.device(device).type != "cpu":
        workers = 1  # one process per GPU: a batch of trajectories fills it better than processes
    workers = max(1, min(workers or os.cpu_count() or 1, len(chunks) or 1))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="generate", unit="traj")
        bar.write(f"{len(wanted) - len(todo)} of {len(wanted)} trajectories exist; simulating {len(todo)}")
    settings = cfg.to_dict()
    jobs = []
    for c in chunks:
        part = sample_part(family, c[0][1]) if family is not None else None
        chunk_settings = part_config(cfg, part).to_dict() if part is not None else settings
        jobs.append((chunk_settings, c, [job in missing for job in c], str(out), compile, device, part))
    if workers == 1:
        results = map(_simulate_chunk, jobs)
        for done in results:
            bar and bar.update(len(done))
    elif jobs:
        _run_in_processes(jobs, workers, bar)
    if bar is not None:
        bar.close()
    failed = [failed_path(out, s, seed) for s, seed in wanted if failed_path(out, s, seed).exists()]
    if failed and progress:
        print(
            f"{len(failed)} of {len(wanted)} runs blew up and are set aside in <split>/{FAILED}/ "
            f"(not part of the dataset): "
            + ", ".join(str(p.relative_to(out)) for p in failed[:5])
            + (" ..." if len(failed) > 5 else "")
        )
    return [trajectory_path(out, s, seed) for s, seed in wanted if trajectory_path(out, s, seed).exists()]
