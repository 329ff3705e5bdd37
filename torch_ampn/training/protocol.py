"""What the forming LightningModule asks of its data module: a declared interface, not ``hasattr``."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Protocol, runtime_checkable

import torch

from torch_ampn.data.trajectory import Trajectory
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData


@runtime_checkable
class ForecastDataSource(Protocol):
    """The methods :class:`~torch_ampn.training.SurrogateLightningModule` calls on ``trainer.datamodule``.

    :class:`~torch_ampn.training.AMPNDataModule` implements them. A data module of your own that
    implements them all gets what the module does with them: the model checked against the data
    before a fit, normalisation statistics from its training windows, the mesh check of test and
    predict, and the setting-aware baselines of ``test``. One that does not (any other
    ``LightningDataModule``) can still validate and test a fitted model: the mesh check and the
    setting-aware baselines are then skipped, and a fit from scratch is refused in one line.
    """

    def check_model(self, surrogate: torch.nn.Module) -> None:
        """Raise ``ValueError`` if the model's component, gripper or prior settings do not fit the data."""

    def statistics_samples(self, count: int) -> Iterable[HierarchicalData]:
        """About ``count`` training samples for the normalisation statistics."""

    def mesh_keys(self, split: str) -> dict[str, int]:
        """Topology key -> node count of every mesh of ``split`` (``"train"``, ..., ``"predict"``)."""

    def check_meshes(self, known: dict[str, int], split: str) -> None:
        """Raise ``ValueError`` naming the first file of ``split`` whose mesh is not in ``known``."""

    def training_trajectories(self) -> list[Trajectory]:
        """Every training trajectory (the setting-aware baselines are fitted on them)."""

    def fitted_baselines(self) -> dict[str, Any]:
        """Baselines already fitted on the training split, by name (reused, not fitted again)."""


def forecast_source(datamodule: Any) -> ForecastDataSource | None:
    """``datamodule`` if it implements :class:`ForecastDataSource`, else ``None``."""
    return datamodule if isinstance(datamodule, ForecastDataSource) else None
