"""``FitProgress``: one line every so many steps with the whole fit's ETA, compiling included.

Lightning's progress bar counts the steps of an epoch; a fit of ``max_steps`` over many
epochs (and a first step that compiles for minutes on a cold cache) needs the whole fit's
count and an honest ETA. The ``torch-ampn`` CLI adds this callback to every fit
(``--progress.every_n_steps``, 0 turns it off).
"""

from __future__ import annotations

import sys
import time
from typing import Any

from lightning.pytorch.callbacks import Callback


def format_seconds(seconds: float) -> str:
    """``"42 s"``, ``"7 min 05 s"`` or ``"1 h 02 min"``."""
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class FitProgress(Callback):
    """Print ``step i/N``, the recent step rate and the ETA of the remaining steps.

    The ETA is the remaining steps at the rate of the steps since the last line, validation
    included; the first step is reported on its own (it compiles the training step when
    ``model.compile_network`` is on, which on a cold Inductor cache takes minutes on 2 cores).

    Args:
        every_n_steps: Steps between lines (0: no lines).
        slow_first_step: A first step at least this long (seconds) is reported as compiling.
    """

    def __init__(self, every_n_steps: int = 250, slow_first_step: float = 20.0) -> None:
        super().__init__()
        self.every_n_steps = every_n_steps
        self.slow_first_step = slow_first_step
        self._start: float | None = None
        self._last: tuple[int, float] | None = None

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        """Start the clock."""
        self._start = time.perf_counter()
        self._last = None

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, index: int) -> None:
        """Every ``every_n_steps`` steps (and at the last): one progress line."""
        if not self.every_n_steps or not trainer.is_global_zero or self._start is None:
            return
        step, now, planned = trainer.global_step, time.perf_counter(), trainer.max_steps
        if self._last is None:
            first = now - self._start
            if first >= self.slow_first_step:
                why = " (compiling the training step)" if pl_module.hparams.get("compile_network") else ""
                self._print(f"[fit] the first step took {format_seconds(first)}{why}")
            self._last = (step, now)
            return
        if step % self.every_n_steps and step != planned:
            return
        last_step, last_time = self._last
        rate = (step - last_step) / max(now - last_time, 1e-9)  # steps/s, validation included
        total = f"/{planned}" if planned and planned > 0 else ""
        eta = f", ETA {format_seconds((planned - step) / rate)}" if planned and planned > step else ""
        elapsed = format_seconds(now - self._start)
        self._print(f"[fit] step {step}{total}, {rate:.2f} steps/s, {elapsed} so far{eta}")
        self._last = (step, now)

    @staticmethod
    def _print(line: str) -> None:
        from tqdm.auto import tqdm

        tqdm.write(line, file=sys.stderr)  # between the progress bar's redraws
