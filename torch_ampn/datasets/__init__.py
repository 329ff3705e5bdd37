"""Problems on plain meshes for the generic core: the reach benchmark's steady FE problems."""

from torch_ampn.datasets.reach import (
    PROBLEMS,
    elasticity_sample,
    hop_distance,
    laplace_sample,
    random_mesh,
    reach_sample,
    smoothing_sample,
)

__all__ = [
    "PROBLEMS",
    "elasticity_sample",
    "hop_distance",
    "laplace_sample",
    "random_mesh",
    "reach_sample",
    "smoothing_sample",
]
