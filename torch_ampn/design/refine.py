"""Gradient refinement of a searched setting: projected descent on finite differences, batched.

After :func:`~torch_ampn.design.search.search_settings`, a few descent steps from its best
setting. The gradient of the objective with respect to the settings comes from central
differences: the ``2 D`` shifted settings and the point itself are one batched predictor call
(for the 4 gripper settings, 9 rollouts in one batch). Automatic differentiation of the
rollout is not used: a surrogate with a prior reads a scikit-learn Gaussian process's
prediction of the settings, which torch cannot differentiate, and the embedded simulator's
batched rollout is one forward call either way. Each step then tries a few step lengths along
the negative gradient in one more batch and keeps the best, so an accepted step never raises
the objective (lower is better).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass
class RefineResult:
    """What :func:`refine_settings` found.

    Attributes:
        start: The starting settings ``[D]``.
        start_value: The objective there.
        best: The refined settings ``[D]`` (``start`` where no step helped).
        best_value: The objective there (``<= start_value``).
        history: The objective after each step (the first entry: at ``start``).
        evaluations: Objective values computed (settings predicted).
        steps: Steps taken (a step that improved nothing ends the refinement early).
    """

    start: np.ndarray
    start_value: float
    best: np.ndarray
    best_value: float
    history: list[float] = field(default_factory=list)
    evaluations: int = 0
    steps: int = 0

    @property
    def improvement(self) -> float:
        """``start_value - best_value`` (>= 0)."""
        return self.start_value - self.best_value


def refine_settings(
    objective: Callable[[np.ndarray], np.ndarray],
    bounds: Sequence[tuple[float, float]],
    start: np.ndarray,
    steps: int = 5,
    difference: float = 0.01,
    lengths: Sequence[float] = (0.2, 0.05, 0.0125),
    progress: bool = False,
) -> RefineResult:
    """Descend from ``start`` on a batched ``objective`` (``[M, D] -> [M]``) within ``bounds``.

    The settings are scaled to the unit box. Per step: central differences of half-width
    ``difference`` (clipped to the box, one-sided at its faces) give the gradient ``g``; the
    candidates ``x - l g / |g|_inf`` for each length ``l`` in ``lengths`` (clipped to the box)
    are evaluated at once, and the best replaces ``x`` if it is lower, else the refinement stops.

    Args:
        objective: Values of ``M`` settings at once.
        bounds: ``(low, high)`` per coordinate, ``D`` of them.
        start: The settings to start from ``[D]`` (e.g. :attr:`SearchResult.best`).
        steps: Most descent steps.
        difference: Finite-difference half-width, a fraction of each range.
        lengths: Step lengths tried per step, fractions of each range (largest move of a coordinate).
        progress: Show a progress bar over the steps.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in zip(*bounds, strict=True))
    span = hi - lo
    x = (np.asarray(start, dtype=np.float64).reshape(-1) - lo) / span
    if x.shape != lo.shape:
        raise ValueError(f"start must have {lo.size} settings, got {np.asarray(start).size}")
    if steps < 0 or difference <= 0 or not lengths or min(lengths) <= 0:
        raise ValueError("steps must be >= 0, difference > 0 and lengths positive")
    dim = x.size
    evaluations = 0

    def values(u: np.ndarray) -> np.ndarray:  # unit-box settings [M, D] -> [M]
        nonlocal evaluations
        f = np.asarray(objective(lo + u * span), dtype=np.float64).reshape(-1)
        if f.shape != (u.shape[0],) or not np.isfinite(f).all():
            raise ValueError(f"the objective must give {u.shape[0]} finite values, got {f}")
        evaluations += u.shape[0]
        return f

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="refine", unit="step")
    fx, history, taken = None, [], 0
    try:
        for _ in range(steps):
            up = np.minimum(x + difference, 1.0)
            down = np.maximum(x - difference, 0.0)
            probes = np.repeat(x[None], 2 * dim, 0)
            probes[np.arange(dim), np.arange(dim)] = up
            probes[dim + np.arange(dim), np.arange(dim)] = down
            f = values(np.vstack([x[None], probes]))
            if fx is None:
                fx = float(f[0])
                history.append(fx)
            grad = (f[1 : dim + 1] - f[dim + 1 :]) / np.maximum(up - down, 1e-12)  # [D]
            norm = float(np.abs(grad).max())
            if norm == 0.0:
                break
            candidates = np.clip(x[None] - np.asarray(lengths)[:, None] * grad[None] / norm, 0.0, 1.0)
            fc = values(candidates)
            best = int(np.argmin(fc))
            if fc[best] >= fx:
                break
            x, fx = candidates[best], float(fc[best])
            history.append(fx)
            taken += 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(value=f"{fx:.4g}")
    finally:
        if bar is not None:
            bar.close()
    start_x = np.asarray(start, dtype=np.float64).reshape(-1)
    if fx is None:  # no step asked for: the start's value alone
        fx = float(values(x[None])[0])
        history.append(fx)
    return RefineResult(start_x, history[0], lo + x * span, fx, history, evaluations, taken)


__all__ = ["RefineResult", "refine_settings"]
