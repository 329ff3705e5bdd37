"""The paper's learning-rate schedule: linear warm-up, then exponential decay (stepped per optimiser step)."""

from __future__ import annotations

import math


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
