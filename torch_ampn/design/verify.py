"""Check a design choice with the simulator.

Where the chosen setting ranks among random settings, how well the predictor ranks those
(Spearman, for the chosen measure and for every measure of
:data:`~torch_ampn.design.measures.MEASURES`), and the cost of both ways. With ``repeat`` the
random settings are simulated a second time from a start moved by ``repeat`` mm: the
simulator's rank correlation with itself, ``r``, measures the forming's chaos: a predictor of
the chaos-free measure reaches about ``sqrt(r)`` against one simulated run (``docs/design.md``).
With ``runs = R`` every setting is simulated ``R`` times (all but the first from a start moved
by ``repeat`` mm, each its own perturbation) and judged by its mean measure, whose chaos is
``R`` times smaller in variance: the ceiling rises to about ``sqrt(R r / (1 + (R - 1) r))``
(Spearman-Brown), :meth:`Verification.spearman_ceiling`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from torch import Tensor

from torch_ampn.design.measures import MEASURES, WrinkleOperator, part_quality
from torch_ampn.design.predictors import simulator_predictor
from torch_ampn.design.search import Predictor, SettingsSpace, measure_weights, settings_trajectories
from torch_ampn.sim.config import StampFormingConfig


def _spearman(a: Sequence[float], b: Sequence[float]) -> float:
    """Rank correlation; NaN where either side is constant (no ranking to compare)."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b).statistic)


def _objective(measures: dict[str, np.ndarray], weights: dict[str, float]) -> np.ndarray:
    return sum(w * measures[name] for name, w in weights.items())


def _mean_pairwise_spearman(runs: Sequence[np.ndarray]) -> float:
    """The mean rank correlation over every pair of runs ``[N]`` each (NaN if a pair has none)."""
    pairs = [_spearman(a, b) for i, a in enumerate(runs) for b in runs[i + 1 :]]
    return float(np.mean(pairs)) if pairs else float("nan")


def spearman_ceiling(r: float, runs: int = 1) -> float:
    """About the best Spearman of a chaos-free predictor against the mean of ``runs`` runs.

    ``r`` is the simulator's rank correlation with itself between two single runs. Averaging
    ``runs`` runs shrinks the chaos's variance ``runs`` times, so the mean's correlation with
    another such mean is ``runs r / (1 + (runs - 1) r)`` (Spearman-Brown) and a perfect
    predictor's correlation with it the square root. NaN where ``r`` is not positive.
    """
    if not r > 0:
        return float("nan")
    return float(np.sqrt(runs * r / (1 + (runs - 1) * r)))


@dataclass
class Verification:
    """The simulated check of a chosen setting against ``N`` random ones (lower measure = better).

    Attributes:
        chosen: The chosen settings ``[D]``.
        chosen_predicted: The predictor's objective (the measure searched) of the chosen setting.
        chosen_simulated: The simulator's.
        random_settings: The random settings ``[N, D]``.
        random_predicted: The predictor's objective of each ``[N]``.
        random_simulated: The simulator's ``[N]``.
        rank: 1 + the number of random settings the simulator finds better than the chosen one.
        spearman: Rank correlation of predicted against simulated objective over the random
            settings; NaN where either is the same for all of them (e.g. the mean trajectory).
        predict_seconds: Wall time of the predictor on the chosen and the random settings.
        simulate_seconds: Wall time of the simulator on the chosen and the random settings.
        predicted_measures: Every measure, predicted: name -> ``[1 + N]`` (the chosen first).
        simulated_measures: The same, simulated.
        spearman_by_measure: Predicted against simulated over the random settings, per measure.
        repeat: The start perturbation of the repeated simulation [mm] (0: not repeated).
        repeat_measures: The random settings simulated again: name -> ``[N]``.
        repeat_spearman: Simulated against simulated again, objective (``spearman`` stays below
            about its square root).
        repeat_spearman_by_measure: The same per measure.
        runs: How many times each setting was simulated; the simulated measures, ``rank`` and
            ``spearman`` are the mean over the runs.
        run_measures: With ``runs > 1``: every run's measures, name -> ``[runs, 1 + N]``.
        run_objective: With ``runs > 1``: every run's objective ``[runs, 1 + N]``.
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
    predicted_measures: dict[str, np.ndarray] = field(default_factory=dict)
    simulated_measures: dict[str, np.ndarray] = field(default_factory=dict)
    spearman_by_measure: dict[str, float] = field(default_factory=dict)
    repeat: float = 0.0
    repeat_measures: dict[str, np.ndarray] = field(default_factory=dict)
    repeat_spearman: float = float("nan")
    repeat_spearman_by_measure: dict[str, float] = field(default_factory=dict)
    runs: int = 1
    run_measures: dict[str, np.ndarray] = field(default_factory=dict)
    run_objective: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: Further settings simulated beside the choice (e.g. a refined one): name -> their
    #: ``settings``, ``predicted`` and ``simulated`` objective and ``rank`` among the random ones.
    alternatives: dict[str, dict] = field(default_factory=dict)
    #: The final states ``[N, 3]`` of the chosen setting, predicted and simulated (not in :meth:`to_dict`).
    chosen_final: dict[str, Tensor] = field(default_factory=dict, repr=False)

    @property
    def percentile(self) -> float:
        """The chosen setting's place among the ``N + 1`` simulated, as a fraction (0: the best)."""
        return (self.rank - 1) / (len(self.random_simulated) + 1)

    def spearman_ceiling(self, measure: str | None = None) -> float:
        """About the best ``spearman`` any predictor reaches here, from the simulator's chaos.

        :func:`spearman_ceiling` of ``repeat_spearman`` (or of ``measure``'s) and ``runs``; NaN
        without a repeated simulation.
        """
        r = self.repeat_spearman if measure is None else self.repeat_spearman_by_measure.get(measure, np.nan)
        return spearman_ceiling(r, self.runs)

    def to_dict(self) -> dict:
        """JSON-ready (NaN correlations become ``None``)."""

        def plain(v):
            if isinstance(v, np.ndarray):
                return v.tolist()
            if isinstance(v, dict):
                return {k: plain(x) for k, x in v.items()}
            if isinstance(v, float) and np.isnan(v):
                return None
            return v

        out = {k: plain(v) for k, v in asdict(self).items() if k != "chosen_final"}
        out["percentile"] = self.percentile
        out["spearman_ceiling"] = plain(self.spearman_ceiling())
        out["spearman_ceiling_by_measure"] = {
            n: plain(self.spearman_ceiling(n)) for n in self.repeat_spearman_by_measure
        }
        return out


def _measures_and_finals(
    predict: Predictor, cfg: StampFormingConfig, x: np.ndarray, wrinkle_radius: float | None
) -> tuple[dict[str, np.ndarray], list[Tensor]]:
    trajs = settings_trajectories(cfg, SettingsSpace.from_config(cfg), x)
    finals = [pos[-1] for pos in predict(trajs)]
    wrinkle = WrinkleOperator(trajs[0], wrinkle_radius)  # the settings share the part
    rows = [part_quality(t, pos, wrinkle=wrinkle) for t, pos in zip(trajs, finals, strict=True)]
    return {name: np.array([r[name] for r in rows]) for name in MEASURES}, finals


def measures_of(
    predict: Predictor, cfg: StampFormingConfig, x: np.ndarray, wrinkle_radius: float | None = None
) -> dict[str, np.ndarray]:
    """Every measure of :data:`MEASURES` of the predicted parts of settings ``x [M, D]``: name -> ``[M]``."""
    return _measures_and_finals(predict, cfg, x, wrinkle_radius)[0]


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
    repeat: float = 0.0,
    alternatives: dict[str, np.ndarray] | None = None,
    runs: int = 1,
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
        repeat: Simulate the random settings again from a start moved by up to this many mm
            (e.g. ``1e-6``) and report the simulator's rank correlation with itself (0: don't).
        alternatives: Further settings ``[D]`` by name to simulate and rank in the same run
            (e.g. ``{"refined": refine_settings(...).best}``).
        runs: Simulate every setting this many times, all runs but the first from a start
            moved by ``repeat`` mm (``1e-6`` where ``repeat`` is 0), and judge each setting by
            its mean measure over the runs: the chaos of one run averaged out. ``repeat_spearman``
            is then the mean rank correlation between two runs, with no extra simulation.
    """
    if num_random < 2:
        raise ValueError(
            f"verify needs at least 2 random settings (for a rank correlation), got {num_random}"
        )
    if repeat < 0:
        raise ValueError(f"repeat must be >= 0 mm, got {repeat}")
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    if runs > 1 and repeat == 0:
        repeat = 1e-6
    weights = measure_weights(measure)
    space = SettingsSpace.from_config(cfg)
    chosen = np.asarray(chosen, dtype=np.float64).reshape(-1)
    randoms = space.sample(num_random, seed)
    others = {k: np.asarray(v, dtype=np.float64).reshape(-1) for k, v in (alternatives or {}).items()}
    x = np.vstack([chosen, randoms, *others.values()])
    start = time.perf_counter()
    pred, pred_finals = _measures_and_finals(predict, cfg, x, wrinkle_radius)
    predict_seconds = time.perf_counter() - start
    start = time.perf_counter()
    each_run = []  # [runs] of name -> [len(x)]
    for k in range(runs):
        simulator = simulator_predictor(
            cfg, compile=compile, progress=progress, perturbation=repeat if k else 0.0, seed_offset=k * len(x)
        )
        measures, finals = _measures_and_finals(simulator, cfg, x, wrinkle_radius)
        each_run.append(measures)
        if k == 0:
            sim_finals = finals  # the unperturbed run's final states
    sim = {name: np.mean([m[name] for m in each_run], axis=0) for name in MEASURES}
    simulate_seconds = time.perf_counter() - start
    pred_obj, sim_obj = _objective(pred, weights), _objective(sim, weights)
    n = num_random + 1  # the chosen and the random settings; the alternatives after them
    ranked = {
        name: {"settings": others[name], "predicted": float(pred_obj[n + i]),
               "simulated": float(sim_obj[n + i]), "rank": 1 + int((sim_obj[1:n] < sim_obj[n + i]).sum())}
        for i, name in enumerate(others)
    }  # fmt: skip
    pred = {k: v[:n] for k, v in pred.items()}
    sim = {k: v[:n] for k, v in sim.items()}
    pred_obj, sim_obj = pred_obj[:n], sim_obj[:n]
    check = Verification(
        chosen=chosen,
        chosen_predicted=float(pred_obj[0]),
        chosen_simulated=float(sim_obj[0]),
        random_settings=randoms,
        random_predicted=pred_obj[1:],
        random_simulated=sim_obj[1:],
        rank=1 + int((sim_obj[1:] < sim_obj[0]).sum()),
        spearman=_spearman(pred_obj[1:], sim_obj[1:]),
        predict_seconds=predict_seconds,
        simulate_seconds=simulate_seconds,
        predicted_measures=pred,
        simulated_measures=sim,
        spearman_by_measure={n: _spearman(pred[n][1:], sim[n][1:]) for n in MEASURES},
        alternatives=ranked,
        chosen_final={"predicted": pred_finals[0], "simulated": sim_finals[0]},
    )
    randoms_of = [{k: v[1:n] for k, v in m.items()} for m in each_run]  # [runs] of name -> [N]
    if runs == 1 and repeat > 0:  # one more run, of the random settings only
        again = simulator_predictor(cfg, compile=compile, progress=progress, perturbation=repeat)
        randoms_of.append(measures_of(again, cfg, randoms, wrinkle_radius))
    if len(randoms_of) > 1:
        check.repeat = repeat
        check.repeat_measures = randoms_of[1]
        check.repeat_spearman = _mean_pairwise_spearman([_objective(m, weights) for m in randoms_of])
        check.repeat_spearman_by_measure = {
            name: _mean_pairwise_spearman([m[name] for m in randoms_of]) for name in MEASURES
        }
    if runs > 1:
        check.runs = runs
        check.run_measures = {name: np.stack([m[name][:n] for m in each_run]) for name in MEASURES}
        check.run_objective = np.stack([_objective(m, weights)[:n] for m in each_run])
    return check


__all__ = ["Verification", "measures_of", "spearman_ceiling", "verify_choice"]
