"""Search the process settings for the best part: batched predictions and differential evolution.

A design study asks a *predictor* (a trained surrogate, a classical baseline such as POD + GP,
or the simulator itself) for the formed part of many settings at once and judges each with a
part-quality measure (:mod:`torch_ampn.design.measures`). The settings of the embedded
process are a vector ``x = [positions (G), forces (G)]``: each gripper's place along its free
edge (a fraction) and its pulling force (N), within the simulator config's ranges
(:class:`SettingsSpace`). :func:`search_settings` minimises any batched objective of ``x``
with scipy's ``differential_evolution(vectorized=True)``; :func:`settings_objective` builds
the objective "measure of the predicted part".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from torch import Tensor

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.design.measures import MEASURES, WrinkleOperator, part_quality
from torch_ampn.sim.config import StampFormingConfig

#: Predicted positions ``[S, N, 3]`` of each given setting trajectory, the formed part last: the
#: whole rollout (``S = T + 1``) or the formed part alone (``S = 1``). Searches read ``[-1]`` only.
Predictor = Callable[[Sequence[Trajectory]], list[Tensor]]


@dataclass(frozen=True)
class SettingsSpace:
    """The process settings of a stamp-forming config: gripper positions then forces.

    Attributes:
        num_grippers: ``G``.
        position_range: Each gripper's place along its free edge, a fraction in ``[0, 1]``.
        force_range: Each gripper's pulling force, N.
    """

    num_grippers: int
    position_range: tuple[float, float]
    force_range: tuple[float, float]

    @classmethod
    def from_config(cls, cfg: StampFormingConfig) -> SettingsSpace:
        """The ranges ``cfg`` samples its training settings from."""
        lo, hi = cfg.gripper_position_range
        flo, fhi = cfg.gripper_force_range
        return cls(cfg.num_grippers, (float(lo), float(hi)), (float(flo), float(fhi)))

    @property
    def names(self) -> list[str]:
        """``position_0 .. position_{G-1}, force_0 .. force_{G-1}``."""
        g = range(self.num_grippers)
        return [f"position_{i}" for i in g] + [f"force_{i}" for i in g]

    @property
    def bounds(self) -> list[tuple[float, float]]:
        """``(low, high)`` of each coordinate of ``x``."""
        return [self.position_range] * self.num_grippers + [self.force_range] * self.num_grippers

    def sample(self, count: int, seed: int = 0) -> np.ndarray:
        """``count`` settings drawn uniformly from the ranges, ``[count, 2G]``."""
        lo, hi = np.array(self.bounds).T
        return lo + (hi - lo) * np.random.default_rng(seed).random((count, len(lo)))

    def split(self, x: np.ndarray) -> list[tuple[list[float], list[float]]]:
        """``[M, 2G]`` settings as ``(positions, forces)`` pairs (the simulator's ``settings``)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        if x.shape[1] != 2 * self.num_grippers:
            raise ValueError(f"settings need {2 * self.num_grippers} values each, got {x.shape[1]}")
        g = self.num_grippers
        return [(row[:g].tolist(), row[g:].tolist()) for row in x]


def settings_trajectories(cfg: StampFormingConfig, space: SettingsSpace, x: np.ndarray) -> list[Trajectory]:
    """The rollout inputs (:func:`~torch_ampn.sim.process_trajectories`) of settings ``x`` ``[M, 2G]``."""
    from torch_ampn.sim import process_trajectories

    return process_trajectories(cfg, space.split(x))


def measure_weights(measure: str | dict[str, float]) -> dict[str, float]:
    """``{name: weight}`` of a measure name or of a weighted sum.

    Every name is checked against :data:`~torch_ampn.design.measures.MEASURES`; a ``ValueError``
    names the unknown ones.
    """
    weights = {measure: 1.0} if isinstance(measure, str) else {k: float(v) for k, v in measure.items()}
    unknown = sorted(set(weights) - set(MEASURES))
    if unknown or not weights:
        raise ValueError(f"measure must be among {sorted(MEASURES)}, got {unknown or 'none'}")
    return weights


def settings_objective(
    predict: Predictor,
    cfg: StampFormingConfig,
    measure: str | dict[str, float] = "wrinkle_rms",
    wrinkle_radius: float | None = None,
) -> Callable[[np.ndarray], np.ndarray]:
    """The batched objective ``x [M, 2G] -> [M]``: a measure (or weighted sum) of the predicted part.

    Args:
        predict: The predictor (positions per setting trajectory; the last state is judged).
        cfg: The process (mesh, tools, ranges).
        measure: A name of :data:`~torch_ampn.design.measures.MEASURES`, or ``{name: weight}``.
        wrinkle_radius: See :func:`~torch_ampn.design.measures.wrinkle_field`.
    """
    weights = measure_weights(measure)
    space = SettingsSpace.from_config(cfg)
    operator: list[WrinkleOperator | None] = [None]

    def objective(x: np.ndarray) -> np.ndarray:
        trajs = settings_trajectories(cfg, space, x)
        rollouts = predict(trajs)
        values = []
        for traj, pos in zip(trajs, rollouts, strict=True):
            if operator[0] is None or not operator[0].applies_to(traj):
                operator[0] = WrinkleOperator(traj, wrinkle_radius)  # one per part: the settings share it
            q = part_quality(traj, pos[-1], wrinkle=operator[0], names=weights)  # only what is weighed
            values.append(sum(w * q[name] for name, w in weights.items()))
        return np.asarray(values, dtype=np.float64)

    return objective


@dataclass
class SearchResult:
    """What :func:`search_settings` found.

    Attributes:
        best: The best settings ``[D]``.
        best_value: The objective there.
        settings: Every evaluated setting ``[E, D]``, in evaluation order.
        values: Their objective values ``[E]``.
        generations: Number of generations run.
    """

    best: np.ndarray
    best_value: float
    settings: np.ndarray
    values: np.ndarray
    generations: int
    history: list[float] = field(default_factory=list)

    def top(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` best distinct evaluated settings ``[k, D]`` and their values ``[k]``."""
        _, first = np.unique(self.settings, axis=0, return_index=True)
        order = first[np.argsort(self.values[first], kind="stable")][:k]
        return self.settings[order], self.values[order]


def search_settings(
    objective: Callable[[np.ndarray], np.ndarray],
    bounds: Sequence[tuple[float, float]],
    maxiter: int = 20,
    popsize: int = 8,
    seed: int = 0,
    progress: bool = False,
) -> SearchResult:
    """Minimise a batched ``objective`` (``[M, D] -> [M]``) within ``bounds`` by differential evolution.

    scipy's ``differential_evolution`` with ``vectorized=True`` (one call per generation of
    ``popsize * D`` settings), Latin-hypercube initialisation, no gradient polish at the end.

    Args:
        objective: Values of ``M`` settings at once.
        bounds: ``(low, high)`` per coordinate, ``D`` of them.
        maxiter: Generations after the initial population.
        popsize: Population size per coordinate.
        seed: Seed of the search.
        progress: Show a progress bar over the generations.
    """
    from scipy.optimize import differential_evolution

    seen_x: list[np.ndarray] = []
    seen_f: list[np.ndarray] = []
    history: list[float] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=maxiter + 1, desc="design search", unit="gen")

    def batched(x_t: np.ndarray) -> np.ndarray:  # scipy passes [D, S]
        x = np.atleast_2d(x_t.T)
        f = np.asarray(objective(x), dtype=np.float64).reshape(-1)
        if f.shape != (x.shape[0],) or not np.isfinite(f).all():
            raise ValueError(f"the objective must give {x.shape[0]} finite values, got {f}")
        seen_x.append(x.copy())
        seen_f.append(f)
        history.append(float(np.min(np.concatenate(seen_f))))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(best=f"{history[-1]:.4g}")
        return f

    try:
        result = differential_evolution(
            batched,
            bounds=list(bounds),
            maxiter=maxiter,
            popsize=popsize,
            seed=seed,
            vectorized=True,
            updating="deferred",
            polish=False,
            init="latinhypercube",
            tol=0.0,
        )
    finally:
        if bar is not None:
            bar.close()
    values = np.concatenate(seen_f)
    settings = np.concatenate(seen_x)
    i = int(np.argmin(values))
    return SearchResult(settings[i], float(values[i]), settings, values, int(result.nit), history)


def parameter_map(
    objective: Callable[[np.ndarray], np.ndarray],
    space: SettingsSpace,
    best: np.ndarray,
    axes: tuple[int, int],
    points: int = 9,
) -> dict:
    """The objective on a ``points x points`` grid of two settings (``axes``), the others at ``best``.

    Returns ``{"axes": [name, name], "a": [points], "b": [points], "values": [points, points]}``
    (``values[i, j]`` at ``a[i]``, ``b[j]``).
    """
    lo, hi = np.array(space.bounds).T
    a, b = (np.linspace(lo[i], hi[i], points) for i in axes)
    grid = np.repeat(best[None], points * points, 0)
    ga, gb = np.meshgrid(a, b, indexing="ij")
    grid[:, axes[0]], grid[:, axes[1]] = ga.ravel(), gb.ravel()
    return {
        "axes": [space.names[i] for i in axes],
        "a": a,
        "b": b,
        "values": objective(grid).reshape(points, points),
    }


__all__ = [
    "parameter_map",
    "Predictor",
    "SearchResult",
    "SettingsSpace",
    "search_settings",
    "measure_weights",
    "settings_objective",
    "settings_trajectories",
]
