"""The paper's learning-rate schedule: linear warm-up, then exponential decay (stepped per optimiser step)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable


def warmup_exponential_decay(
    step: int, warmup_steps: int, total_steps: int, lr: float, final_lr: float
) -> float:
    r"""Learning-rate factor (multiplies ``lr``) after ``step`` optimiser steps.

    * ``step < warmup_steps``: linear warm-up, :math:`(s + 1) / W` (so the first step already
      uses a small non-zero rate and step ``W - 1`` uses ``lr``);
    * afterwards exponential decay from ``lr`` to ``final_lr`` over the remaining
      ``total_steps - warmup_steps`` steps:
      :math:`(\text{final\_lr} / \text{lr})^{(s - W) / (S - W)}`, held at ``final_lr / lr`` beyond ``S``.

    Args:
        step: Optimiser steps taken so far (0-based).
        warmup_steps: ``W`` (0: no warm-up).
        total_steps: ``S``, all optimiser steps of the run.
        lr: Peak learning rate (paper: 1e-4).
        final_lr: Learning rate at ``S`` (paper: 1e-5).
    """
    if lr <= 0 or final_lr <= 0:
        raise ValueError(f"lr and final_lr must be > 0, got {lr} and {final_lr}")
    if warmup_steps < 0 or total_steps < 1:
        raise ValueError(f"need warmup_steps >= 0 and total_steps >= 1, got {warmup_steps}, {total_steps}")
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    decay_steps = max(total_steps - warmup_steps, 1)
    progress = min((step - warmup_steps) / decay_steps, 1.0)
    return math.exp(progress * math.log(final_lr / lr))


class WarmupExponentialDecay:
    r"""LR factor for ``LambdaLR``: :func:`warmup_exponential_decay`, optionally under a time budget.

    Without ``time_remaining`` it is exactly :func:`warmup_exponential_decay`. With it (a callable
    giving the seconds left for training, e.g. Lightning's ``Timer.time_remaining`` when
    ``trainer.max_time`` is set), the decay follows whichever runs out first, the steps or the
    time: at the first decay step it notes the time left, :math:`R_0`, and from then on the
    decay progress is

    .. math::
        p = \min\left(1, \max\left(\frac{s - W}{S - W}, \frac{t - t_0}{R_0}\right)\right),
        \qquad \text{factor} = (\text{final\_lr} / \text{lr})^{p},

    so that a run stopped by its time limit ends at ``final_lr`` just as one that runs all its
    steps. The warm-up always counts steps. A time-limited decay depends on the machine's speed
    (the same config decays faster on a slower machine); without a time limit it is reproducible.

    Args:
        warmup_steps: ``W``.
        total_steps: ``S``.
        lr: Peak learning rate.
        final_lr: Learning rate at the end.
        time_remaining: Seconds of training left, or ``None`` for no limit (``None`` returned by
            the callable also means no limit).
        clock: Monotonic clock in seconds (the one ``time_remaining`` uses).
    """

    def __init__(
        self,
        warmup_steps: int,
        total_steps: int,
        lr: float,
        final_lr: float,
        time_remaining: Callable[[], float | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        warmup_exponential_decay(0, warmup_steps, total_steps, lr, final_lr)  # checks the arguments
        self.warmup_steps = warmup_steps
        self.total_steps = total_steps
        self.lr = lr
        self.final_lr = final_lr
        self.time_remaining = time_remaining
        self.clock = clock
        self._decay_start: tuple[float, float] | None = None  # (t_0, R_0)

    def time_progress(self) -> float:
        """Fraction of the time budget used since the first decay step (0 without a budget)."""
        if self._decay_start is None:
            return 0.0
        t0, r0 = self._decay_start
        return 1.0 if r0 <= 0 else (self.clock() - t0) / r0

    def __call__(self, step: int) -> float:
        """Factor (multiplies ``lr``) after ``step`` optimiser steps."""
        factor = warmup_exponential_decay(step, self.warmup_steps, self.total_steps, self.lr, self.final_lr)
        if step < self.warmup_steps or self.time_remaining is None:
            return factor
        if self._decay_start is None:
            remaining = self.time_remaining()
            if remaining is None:
                self.time_remaining = None
                return factor
            self._decay_start = (self.clock(), float(remaining))
        # both factors fall with their progress, so the smaller one is the one further along
        by_time = math.exp(min(self.time_progress(), 1.0) * math.log(self.final_lr / self.lr))
        return min(factor, by_time)
