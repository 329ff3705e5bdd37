"""Does a trajectory depend on how its dataset was made? One job against shards, in mm.

    python benchmarks/shard_bits.py --num-train 8 --out benchmarks/results/shard_bits.json

Generates the same dataset (the default simulator, compiled, in chunks of ``--batch``) three
ways into a scratch folder: one job with two worker processes, the same split in two shards
(``--shard 0/2`` and ``1/2``, each in process, as two machines would), and one job with one
worker. Prints and writes the largest difference of any node position at any saved step between
the one-job files and each other way (0.0 where the files are the same bit for bit), next to
the simulator's chaos floor (two runs of a setting from starts 1e-6 mm apart, about 0.05 mm on
data version 3).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import torch

from torch_ampn.data import Trajectory
from torch_ampn.sim import generate_dataset


def largest_difference(a: Path, b: Path) -> tuple[float, int]:
    """``(largest |x_a - x_b| in mm over every file, node and step, files that differ at all)``."""
    worst, differ = 0.0, 0
    for path in sorted(a.glob("train/*.pt")):
        pa, pb = Trajectory.load(path).pos, Trajectory.load(b / path.relative_to(a)).pos  # [T+1, N, 3]
        gap = float((pa.double() - pb.double()).abs().max())
        worst, differ = max(worst, gap), differ + (gap > 0)
    return worst, differ


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--num-train", type=int, default=8)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/shard_bits.json"))
    args = parser.parse_args()
    sizes = (args.num_train, 0, 0)
    options = dict(batch=args.batch, progress=False)
    root = Path(tempfile.mkdtemp(prefix="shard_bits_"))
    try:
        start = time.perf_counter()
        generate_dataset(root / "one_job", *sizes, workers=2, **options)
        for i in (0, 1):
            generate_dataset(root / "shards", *sizes, workers=1, shard=(i, 2), **options)
        generate_dataset(root / "one_worker", *sizes, workers=1, **options)
        seconds = time.perf_counter() - start
        rows = {}
        for name in ("shards", "one_worker"):
            worst, differ = largest_difference(root / "one_job", root / name)
            rows[name] = {"largest_difference_mm": worst, "files_that_differ": differ}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    record = {
        "trajectories": args.num_train,
        "batch": args.batch,
        "against_one_job_with_two_workers": rows,
        "seconds": seconds,
        "torch": torch.__version__,
        "date": time.strftime("%Y-%m-%d"),
    }
    for name, row in rows.items():
        print(f"{name:12s}: largest difference {row['largest_difference_mm']:.3g} mm, "
              f"{row['files_that_differ']} of {args.num_train} files differ")  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=1))
    tmp.replace(args.out)


if __name__ == "__main__":
    main()
