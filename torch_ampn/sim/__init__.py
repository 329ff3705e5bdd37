"""The embedded quarter double-dome stamp-forming simulator that makes the default dataset."""

from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.dataset import SPLIT_SEED_OFFSET, generate_dataset, trajectory_path
from torch_ampn.sim.simulate import build_mesh, process_trajectory, simulate, simulate_batch

__all__ = [
    "SPLIT_SEED_OFFSET",
    "StampFormingConfig",
    "build_mesh",
    "generate_dataset",
    "process_trajectory",
    "simulate",
    "simulate_batch",
    "trajectory_path",
]
