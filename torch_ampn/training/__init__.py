"""Training with Lightning: one module per model, data module, schedule, reports and the ``torch-ampn`` CLI.

Needs the ``train`` extra (``pip install torch-ampn[train]``).
"""

from torch_ampn.training.checkpoint import load_module
from torch_ampn.training.datamodule import AMPNDataModule
from torch_ampn.training.direct_module import DirectLightningModule
from torch_ampn.training.items import RolloutDataset, RolloutItem
from torch_ampn.training.module import SurrogateLightningModule
from torch_ampn.training.next_step_module import NextStepLightningModule
from torch_ampn.training.protocol import ForecastDataSource
from torch_ampn.training.report import TestReport
from torch_ampn.training.schedule import WarmupExponentialDecay, warmup_exponential_decay

__all__ = [
    "AMPNDataModule",
    "DirectLightningModule",
    "ForecastDataSource",
    "NextStepLightningModule",
    "RolloutDataset",
    "RolloutItem",
    "SurrogateLightningModule",
    "TestReport",
    "WarmupExponentialDecay",
    "load_module",
    "warmup_exponential_decay",
]
