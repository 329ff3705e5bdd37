"""Tensor memory of a paper-resolution hierarchy, training window and trajectory (prints MB).

python benchmarks/paper_memory.py
"""

import torch

from torch_ampn.data import HierarchyCache, step_sample
from torch_ampn.sim import StampFormingConfig, process_trajectory
from torch_ampn.transforms import ComponentRadiusGraph

cfg = StampFormingConfig.paper()
traj = process_trajectory(cfg, seed=0)
h = HierarchyCache(None, max_levels=4)(traj)


def nbytes(data):
    total = 0
    for store in data.stores:
        for v in store.values():
            if torch.is_tensor(v):
                total += v.numel() * v.element_size()
    return total


hier = nbytes(h)
w = ComponentRadiusGraph(3.0, 3)(step_sample(traj, 25, h))
print("nodes", traj.num_nodes, "levels", h.num_levels)
print("hierarchy MB", hier / 1e6, "window MB (incl. shared hierarchy tensors)", nbytes(w) / 1e6)
print("trajectory file MB", traj.pos.numel() * 4 / 1e6)
