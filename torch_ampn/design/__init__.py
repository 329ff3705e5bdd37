"""Design studies: judge a formed part, search the process settings, check the choice with the simulator.

* :mod:`~torch_ampn.design.measures`: wrinkles, draw-in, shear, penetration of a formed part.
* :mod:`~torch_ampn.design.search`: the settings space and a batched differential-evolution search.
* :mod:`~torch_ampn.design.predictors`: a surrogate, a baseline or the simulator as the predictor.
* :mod:`~torch_ampn.design.refine`: descent from the searched setting on batched finite differences.
* :mod:`~torch_ampn.design.verify`: the simulated check of a choice.
* :mod:`~torch_ampn.design.plots`: a measure's field on the plies, the parameter map, the check.
"""

from torch_ampn.design.measures import (
    MEASURES,
    WrinkleOperator,
    draw_in_field,
    median_edge_length,
    part_quality,
    penetration_field,
    ply_components,
    shear_field,
    wrinkle_field,
)
from torch_ampn.design.plots import (
    FIELDS,
    field_of,
    measure_field,
    plot_measure_maps,
    plot_parameter_map,
    plot_verification,
)
from torch_ampn.design.predictors import baseline_predictor, simulator_predictor, surrogate_predictor
from torch_ampn.design.refine import RefineResult, refine_settings
from torch_ampn.design.search import (
    Predictor,
    SearchResult,
    SettingsSpace,
    measure_weights,
    parameter_map,
    search_settings,
    settings_objective,
    settings_trajectories,
)
from torch_ampn.design.verify import Verification, measures_of, spearman_ceiling, verify_choice

__all__ = [
    "FIELDS",
    "MEASURES",
    "Predictor",
    "RefineResult",
    "SearchResult",
    "SettingsSpace",
    "Verification",
    "WrinkleOperator",
    "baseline_predictor",
    "draw_in_field",
    "field_of",
    "measure_field",
    "measures_of",
    "median_edge_length",
    "part_quality",
    "parameter_map",
    "penetration_field",
    "plot_measure_maps",
    "plot_parameter_map",
    "plot_verification",
    "ply_components",
    "refine_settings",
    "search_settings",
    "measure_weights",
    "settings_objective",
    "settings_trajectories",
    "shear_field",
    "spearman_ceiling",
    "simulator_predictor",
    "surrogate_predictor",
    "verify_choice",
    "wrinkle_field",
]
