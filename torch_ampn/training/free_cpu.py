"""``FollowFreeCpu``: the training steps run on the threads other processes leave free."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any

from lightning.pytorch.callbacks import Callback

from torch_ampn.utils.threads import follow_free_cpu


class FollowFreeCpu(Callback):
    """Run the fit inside :func:`~torch_ampn.utils.threads.follow_free_cpu`, one look per batch.

    On the CPU, torch's spinning threads are the fastest on a quiet machine and collapse when
    another process holds a core; this callback sets their number to the cores other processes
    leave free, and restores torch's count when the fit ends.
    :class:`~torch_ampn.training.SurrogateLightningModule` adds it to every Trainer
    (``configure_callbacks``); ``AMPN_THREADS=off`` turns it off.
    """

    def __init__(self) -> None:
        super().__init__()
        self._block = ExitStack()
        self._threads: Any = None  # the governor while a fit runs

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        """Enter the block (on the CPU)."""
        self._block.close()
        self._threads = self._block.enter_context(follow_free_cpu(pl_module.device))

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        """Look at the CPU if it is time to."""
        if self._threads is not None:
            self._threads.step()

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        """Restore torch's thread count."""
        self._leave()

    def on_exception(self, trainer: Any, pl_module: Any, exception: BaseException) -> None:
        """Restore torch's thread count after a failed or interrupted fit too."""
        self._leave()

    def _leave(self) -> None:
        self._threads = None
        self._block.close()
