"""Fault injection for tests of a fit's recovery: a callback that kills its own process."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import lightning as L


class SigkillAtStep(L.Callback):
    """Kills the training process with ``SIGKILL`` (as ``kill -9``) before global step ``step``.

    Nothing is cleaned up, no checkpoint is written on the way out: what a crashed or killed
    job leaves behind. Kills only once ``expect`` (e.g. the ``last.ckpt`` the run should have
    written by then) exists, else raises, so a test cannot pass by killing too early. Use it by
    ``class_path`` (``torch_ampn.training.faults.SigkillAtStep``) in ``trainer.callbacks``.

    Args:
        step: Optimizer steps done when the process is killed.
        expect: A file that must exist at that point.
    """

    def __init__(self, step: int, expect: str | None = None) -> None:
        self.step = step
        self.expect = expect

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: Any, batch: Any, batch_idx: int) -> None:
        """Kill the process if ``step`` optimizer steps are done."""
        if trainer.global_step != self.step:
            return
        if self.expect is not None and not Path(self.expect).is_file():
            raise RuntimeError(f"SigkillAtStep: {self.expect} does not exist at step {self.step}")
        os.kill(os.getpid(), signal.SIGKILL)
