"""Design studies: judge a formed part, search the process settings, check the choice with the simulator."""

from torch_ampn.design.measures import (
    MEASURES,
    draw_in_field,
    median_edge_length,
    part_quality,
    penetration_field,
    ply_components,
    shear_field,
    wrinkle_field,
)

__all__ = [
    "MEASURES",
    "draw_in_field",
    "median_edge_length",
    "part_quality",
    "penetration_field",
    "ply_components",
    "shear_field",
    "wrinkle_field",
]
