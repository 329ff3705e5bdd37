"""Loading a forming surrogate's Lightning checkpoint as the module of its model, old checkpoints included."""

from __future__ import annotations

import inspect
import os
from typing import Any

import torch

from torch_ampn.training.direct_module import DirectLightningModule
from torch_ampn.training.module import SurrogateLightningModule, checkpoint_model
from torch_ampn.training.next_step_module import NextStepLightningModule
from torch_ampn.utils.io import load_torch_file

#: The Lightning module of each model name (``checkpoint["torch_ampn_model"]``, ``data.mode``).
MODULES: dict[str, type[SurrogateLightningModule]] = {
    NextStepLightningModule.MODEL: NextStepLightningModule,
    DirectLightningModule.MODEL: DirectLightningModule,
}


def module_defaults(module_class: type[SurrogateLightningModule]) -> dict[str, Any]:
    """Every argument ``module_class`` takes (its own and its bases'), with its default."""
    defaults: dict[str, Any] = {}
    for klass in reversed(module_class.__mro__):
        if issubclass(klass, SurrogateLightningModule):
            for name, p in inspect.signature(klass.__init__).parameters.items():
                if p.default is not inspect.Parameter.empty:
                    defaults[name] = p.default
    return defaults


def module_class(
    checkpoint: dict[str, Any], path: str | os.PathLike = "checkpoint"
) -> type[SurrogateLightningModule]:
    """The module class of a loaded checkpoint; ``ValueError`` naming ``path`` for an unknown model."""
    name = checkpoint_model(checkpoint)
    if name not in MODULES:
        raise ValueError(f"{path}: model {name!r} is none of torch-ampn's ({', '.join(MODULES)})")
    return MODULES[name]


def module_arguments(hparams: dict[str, Any], module_class: type[SurrogateLightningModule]) -> dict[str, Any]:
    """The saved hyper-parameters ``module_class`` takes.

    Checkpoints written before the split into one module per model (2026-12) hold both
    models' arguments and a ``mode``; the other model's were unused and are dropped here, as
    are Lightning's ``_class_path`` and ``_instantiator``.
    """
    accepted = module_defaults(module_class)
    return {k: v for k, v in hparams.items() if k in accepted}


def load_module(
    path: str | os.PathLike,
    map_location: str | torch.device | None = None,
    strict: bool | None = None,
    expected: type[SurrogateLightningModule] | None = None,
    **overrides: Any,
) -> SurrogateLightningModule:
    """Load any torch-ampn Lightning checkpoint as the module of its model, weights included.

    Args:
        path: The ``.ckpt`` file (of either module, or written before the split).
        map_location: Device to move the module to (default: the CPU).
        strict: Strict state-dict loading (default ``True``).
        expected: Refuse, in one line, a checkpoint of a model that is not this class's.
        **overrides: Hyper-parameters that replace the saved ones (e.g. ``output_dir``).

    Raises:
        ValueError: One line naming the file: not a readable checkpoint, an unknown model,
            or not the ``expected`` one.
    """
    checkpoint = load_torch_file(path, "checkpoint")
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise ValueError(f"{path}: not a Lightning checkpoint (no field 'state_dict')")
    klass = module_class(checkpoint, path)
    if expected is not None and not issubclass(klass, expected):
        raise ValueError(
            f"{path}: holds a {klass.MODEL} model, not a {expected.__name__}'s: load it with "
            f"{klass.__name__}.load_from_checkpoint or torch_ampn.training.load_module"
        )
    module = klass(**{**module_arguments(checkpoint.get("hyper_parameters") or {}, klass), **overrides})
    module.on_load_checkpoint(checkpoint)
    module.load_state_dict(checkpoint["state_dict"], strict=True if strict is None else strict)
    if map_location is not None:
        module = module.to(map_location)
    return module
