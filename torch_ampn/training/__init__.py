"""Training and evaluation with Lightning: module, data module, schedule, reports and the ``torch-ampn`` CLI.

Needs the ``train`` extra (``pip install torch-ampn[train]``).
"""

from torch_ampn.training.datamodule import AMPNDataModule
from torch_ampn.training.items import RolloutDataset, RolloutItem
from torch_ampn.training.module import AMPNLightningModule
from torch_ampn.training.protocol import ForecastDataSource
from torch_ampn.training.report import TestReport
from torch_ampn.training.schedule import WarmupExponentialDecay, warmup_exponential_decay

__all__ = [
    "AMPNDataModule",
    "AMPNLightningModule",
    "ForecastDataSource",
    "RolloutDataset",
    "RolloutItem",
    "TestReport",
    "WarmupExponentialDecay",
    "warmup_exponential_decay",
]
