"""The embedded quarter double-dome stamp-forming simulator that makes the default dataset."""

from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.dataset import SPLIT_SEED_OFFSET, generate_dataset, trajectory_path
from torch_ampn.sim.family import PartFamily, part_config, sample_part
from torch_ampn.sim.simulate import (
    build_mesh,
    process_trajectories,
    process_trajectory,
    simulate,
    simulate_batch,
)

__all__ = [
    "PartFamily",
    "SPLIT_SEED_OFFSET",
    "StampFormingConfig",
    "build_mesh",
    "generate_dataset",
    "part_config",
    "process_trajectories",
    "process_trajectory",
    "sample_part",
    "simulate",
    "simulate_batch",
    "trajectory_path",
]
