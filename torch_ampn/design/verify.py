"""Check a design choice with the simulator.

Where the chosen setting ranks among random settings, how well the predictor ranks those
(Spearman), and the cost of both ways.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from torch_ampn.design.predictors import simulator_predictor
from torch_ampn.design.search import Predictor, SettingsSpace, settings_objective
from torch_ampn.sim.config import StampFormingConfig


@dataclass
class Verification:
    """The simulated check of a chosen setting against ``N`` random ones (lower measure = better).

    Attributes:
        chosen: The chosen settings ``[D]``.
        chosen_predicted: The predictor's measure of the chosen setting.
        chosen_simulated: The simulator's.
        random_settings: The random settings ``[N, D]``.
        random_predicted: The predictor's measure of each ``[N]``.
        random_simulated: The simulator's ``[N]``.
        rank: 1 + the number of random settings the simulator finds better than the chosen one.
        spearman: Rank correlation of predicted against simulated measures over the random
            settings; NaN where either is the same for all of them (e.g. the mean trajectory).
        predict_seconds: Wall time of the predictor on the random settings.
        simulate_seconds: Wall time of the simulator on the chosen and the random settings.
    """

    chosen: np.ndarray
    chosen_predicted: float
    chosen_simulated: float
    random_settings: np.ndarray
    random_predicted: np.ndarray
    random_simulated: np.ndarray
    rank: int
    spearman: float
    predict_seconds: float
    simulate_seconds: float

    @property
    def percentile(self) -> float:
        """The chosen setting's place among the ``N + 1`` simulated, as a fraction (0: the best)."""
        return (self.rank - 1) / (len(self.random_simulated) + 1)

    def to_dict(self) -> dict:
        """JSON-ready."""
        out = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()}
        out["spearman"] = None if np.isnan(self.spearman) else self.spearman
        out["percentile"] = self.percentile
        return out


def verify_choice(
    cfg: StampFormingConfig,
    chosen: np.ndarray,
    predict: Predictor,
    measure: str | dict[str, float],
    num_random: int = 16,
    seed: int = 1,
    compile: bool = False,
    wrinkle_radius: float | None = None,
    progress: bool = False,
) -> Verification:
    """Simulate ``chosen`` and ``num_random`` random settings; compare with the predictor's measures.

    Args:
        cfg: The process.
        chosen: The chosen settings ``[D]`` (e.g. :attr:`SearchResult.best`).
        predict: The predictor the choice was made with.
        measure: The measure (name or weights) the choice minimised.
        num_random: ``N``, random settings drawn uniformly from the config's ranges.
        seed: Seed of the random settings.
        compile: Compile the simulator.
        wrinkle_radius: See :func:`~torch_ampn.design.measures.wrinkle_field`.
        progress: Show a progress bar over the simulated batches.
    """
    from scipy.stats import spearmanr

    if num_random < 2:
        raise ValueError(
            f"verify needs at least 2 random settings (for a rank correlation), got {num_random}"
        )
    space = SettingsSpace.from_config(cfg)
    chosen = np.asarray(chosen, dtype=np.float64).reshape(-1)
    randoms = space.sample(num_random, seed)
    predicted = settings_objective(predict, cfg, measure, wrinkle_radius)
    simulated = settings_objective(
        simulator_predictor(cfg, compile=compile, progress=progress), cfg, measure, wrinkle_radius
    )
    start = time.perf_counter()
    pred = predicted(np.vstack([chosen, randoms]))
    predict_seconds = time.perf_counter() - start
    start = time.perf_counter()
    sim = simulated(np.vstack([chosen, randoms]))
    simulate_seconds = time.perf_counter() - start
    constant = next((v for v in (pred[1:], sim[1:]) if np.ptp(v) == 0), None)
    return Verification(
        chosen=chosen,
        chosen_predicted=float(pred[0]),
        chosen_simulated=float(sim[0]),
        random_settings=randoms,
        random_predicted=pred[1:],
        random_simulated=sim[1:],
        rank=1 + int((sim[1:] < sim[0]).sum()),
        spearman=float(spearmanr(pred[1:], sim[1:]).statistic) if constant is None else np.nan,
        predict_seconds=predict_seconds,
        simulate_seconds=simulate_seconds,
    )


__all__ = ["Verification", "verify_choice"]
