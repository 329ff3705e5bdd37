"""Helpers that only the tests use: tiny CLI configs, a checkpoint-callback probe, fault injection.

Importable as ``helpers`` from the tests (pytest puts ``tests/`` on ``sys.path``) and, for the
``class_path`` of :class:`SigkillAtStep` in a CLI subprocess, with ``tests/`` on ``PYTHONPATH``
(:data:`PYTHONPATH`).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

#: ``PYTHONPATH`` for a subprocess that must import this module (e.g. a CLI fit with SigkillAtStep).
PYTHONPATH = os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]).rstrip(
    os.pathsep
)


def tiny_cli_config(
    model: dict[str, Any] | None = None, data: dict[str, Any] | None = None
) -> dict[str, Any]:
    """A ``torch-ampn`` config (as a dict) that fits a d = 8, 2-level model in seconds.

    For the benchmark scripts' end-to-end tests: a CSV logger and a checkpoint callback
    (their folders are set by the scripts), validation rollouts monitored, no XDMF output,
    rollouts on the plain path (no compile; ``model.fast_rollout`` turns the fast path on).
    ``model`` and ``data`` entries are added to (and override) the defaults.
    """
    return {
        "seed_everything": 0,
        "trainer": {
            "accelerator": "cpu",
            "devices": 1,
            "max_steps": 1000,
            "val_check_interval": 1000,
            "check_val_every_n_epoch": None,
            "enable_model_summary": False,
            "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "x"}},
            "callbacks": [
                {
                    "class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                    "init_args": {"dirpath": "x", "monitor": "val/rollout_rmse", "mode": "min"},
                }
            ],
        },
        "model": {
            "hidden_channels": 8,
            "mlp_channels": 8,
            "num_levels": 2,
            "pre_layers": 1,
            "down_layers": 1,
            "solve_layers": 1,
            "post_layers": 1,
            "up_layers": 1,
            "contact_radius": 12.0,
            "contact_k": 1,
            "warmup_steps": 1,
            "statistics_samples": 8,
            "touch_radii": [3.0, 9.0],
            "export_xdmf": False,
            "fast_rollout": False,
            **(model or {}),
        },  # fmt: skip
        "data": {"data_dir": "unused", "min_coarse_nodes": 4, "batch_size": 2, **(data or {})},
    }


def eager_fast_rollout(monkeypatch) -> None:
    """Make the module's and ``rollout(fast=True)``'s fast path run eagerly, for tests of what
    surrounds it (batching, timings tables): compiling it is tested in tests/test_fast_rollout.py."""
    import functools

    import torch_ampn.rollout.cache as fast_rollout_module
    import torch_ampn.rollout.surrogate as choice  # the one caller of cached_fast_rollout

    eager = functools.partial(fast_rollout_module.cached_fast_rollout, compile=False)
    monkeypatch.setattr(choice, "cached_fast_rollout", lambda *a, compile=0, **k: eager(*a, **k))


def checkpoint_steps(callbacks: list, folder) -> tuple[int, int]:
    """The global steps stored in ``folder``'s ``best.ckpt`` and ``last.ckpt`` after a short fit.

    A linear model is fitted 6 steps with ``callbacks``, validating at steps 2, 4 and 6 with a
    ``val/rollout_rmse`` of 1, 2, 3 (worse after the first). For the tests of the checkpoint
    callbacks.
    """

    class WorseningValidation(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.layer = nn.Linear(2, 1)
            self.validations = 0

        def training_step(self, batch: Tensor, batch_idx: int) -> Tensor:
            return self.layer(batch).square().mean()

        def validation_step(self, batch: Tensor, batch_idx: int) -> None:
            self.log("val/rollout_rmse", float(self.validations + 1))

        def on_validation_end(self) -> None:
            self.validations += 1

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

        def train_dataloader(self):
            return torch.utils.data.DataLoader(torch.randn(64, 2), batch_size=1)

        def val_dataloader(self):
            return torch.utils.data.DataLoader(torch.randn(1, 2), batch_size=1)

    trainer = L.Trainer(
        max_steps=6,
        val_check_interval=2,
        check_val_every_n_epoch=None,
        num_sanity_val_steps=0,
        callbacks=callbacks,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(WorseningValidation())
    folder = Path(folder)
    steps = [
        torch.load(folder / name, weights_only=False, map_location="cpu")["global_step"]
        for name in ("best.ckpt", "last.ckpt")
    ]
    return steps[0], steps[1]


class SigkillAtStep(L.Callback):
    """Kills the training process with ``SIGKILL`` (as ``kill -9``) before global step ``step``.

    Nothing is cleaned up, no checkpoint is written on the way out: what a crashed or killed
    job leaves behind. Kills only once ``expect`` (e.g. the ``last.ckpt`` the run should have
    written by then) exists, else raises, so a test cannot pass by killing too early. Use it by
    ``class_path`` (``helpers.SigkillAtStep``, with :data:`PYTHONPATH`) in ``trainer.callbacks``.

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


class PointwiseNetwork(nn.Module):
    """A stand-in for ``AMPNSurrogate(network_class=...)``: a linear map of each fine node's input.

    Built and called as the surrogate builds and calls a network; it records the ``x_dict`` of
    its last call (``last_x_dict``). ``helpers:PositionsNetwork`` asks for the positions too.
    """

    step_encoding = None
    needs_positions = False

    def __init__(
        self,
        fine_in_channels: int,
        num_levels: int = 1,
        noise_channels: int = 3,
        num_step_frequencies: int = 0,
        max_step: int = 1,
        scale: float = 1.0,
    ) -> None:
        super().__init__()
        self.noise_channels, self.out_channels, self.num_layers = noise_channels, 3, 1
        self.linear = nn.Linear(fine_in_channels + noise_channels, 3)
        self.scale = scale
        self.last_x_dict: dict[str, Tensor] = {}

    def forward(self, x_dict, edge_index_dict, edge_attr_dict, noise=None, step=None, **kwargs) -> Tensor:
        self.last_x_dict = dict(x_dict)
        return self.scale * self.linear(torch.cat([x_dict["l0"], noise], dim=-1))


class PositionsNetwork(PointwiseNetwork):
    """:class:`PointwiseNetwork` with ``needs_positions = True``."""

    needs_positions = True
