"""The embedded quarter double-dome stamp-forming simulator that makes the default dataset."""

from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.simulate import build_mesh, process_trajectory, simulate, simulate_batch

__all__ = ["StampFormingConfig", "build_mesh", "process_trajectory", "simulate", "simulate_batch"]
