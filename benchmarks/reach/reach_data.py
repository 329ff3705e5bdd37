"""The reach benchmark's datasets: samples of :mod:`torch_ampn.datasets.reach` with their AMG hierarchies.

A dataset (problem, mesh size) is made once and cached in ``data/reach/`` (regenerated on
demand: nothing is downloaded). Training samples have seeds ``0 .. n - 1``, test samples
``100000 + i``, so the two never share a mesh or data. Every hierarchy of a dataset is cut to
the same number of levels (the fewest any of its meshes has), so that samples batch.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch
from tqdm import tqdm

from torch_ampn.datasets import hop_distance, reach_sample
from torch_ampn.hierarchy import HierarchicalData, level_name
from torch_ampn.transforms import AMGHierarchy

CACHE = Path(os.environ.get("AMPN_REACH_DATA", "data/reach"))
#: Levels at most and the smallest coarse level: coarsen until a handful of nodes is left.
MAX_LEVELS, MIN_COARSE_NODES = 6, 4
TEST_SEED = 100_000


def num_train(size: int) -> int:
    """Training samples at a mesh size: about 256k nodes in all, 16 to 64 meshes."""
    return min(64, max(16, 256_000 // size))


def truncate(h: HierarchicalData, levels: int) -> HierarchicalData:
    """``h`` without its levels ``>= levels`` (and their edges)."""
    for k in range(levels, h.num_levels):
        for key in [t for t in h.edge_types if level_name(k) in (t[0], t[2])]:
            del h[key]
    for k in range(h.num_levels - 1, levels - 1, -1):
        del h[level_name(k)]
    return h


def make(problem: str, size: int, seeds: list[int]) -> list[HierarchicalData]:
    """Hierarchies of the samples with these seeds (each with ``hop [N]``: edges to the nearest source)."""
    transform = AMGHierarchy(max_levels=MAX_LEVELS, min_coarse_nodes=MIN_COARSE_NODES)
    out = []
    for seed in tqdm(seeds, desc=f"{problem} {size} nodes", leave=False):
        data = reach_sample(problem, size, seed)
        data.hop = hop_distance(data.edge_index, data.source, data.num_nodes)
        out.append(transform(data))
    return out


def load(problem: str, size: int, n_train: int | None = None, n_test: int = 4) -> dict:
    """``{"train": [...], "test": [...], "levels": L, "seconds": s}``, from the cache or made now."""
    n_train = n_train or num_train(size)
    path = CACHE / f"{problem}_{size}_{n_train}_{n_test}.pt"
    if path.exists():
        return torch.load(path, weights_only=False)
    start = time.perf_counter()
    train = make(problem, size, list(range(n_train)))
    test = make(problem, size, [TEST_SEED + i for i in range(n_test)])
    levels = min(h.num_levels for h in train + test)
    out = {
        "train": [truncate(h, levels) for h in train],
        "test": [truncate(h, levels) for h in test],
        "levels": levels,
        "seconds": time.perf_counter() - start,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(out, tmp)
    tmp.replace(path)
    return out


def describe(h: HierarchicalData) -> str:
    """``"50625 / 6134 / 388 / 22 nodes"``."""
    return " / ".join(str(h[level_name(k)].num_nodes) for k in range(h.num_levels)) + " nodes"
