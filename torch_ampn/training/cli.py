"""``torch-ampn``: the Lightning CLI (``fit``, ``validate``, ``test``, ``predict``).

    torch-ampn fit --config examples/configs/quickstart.yaml
    torch-ampn test --config examples/configs/quickstart.yaml \
        --ckpt_path outputs/quickstart/checkpoints/best.ckpt
    torch-ampn predict --ckpt_path CKPT --data.predict_file settings.yaml

The model's contact settings and level count are linked into the data module (the
training windows are built with the same contact edges the model rolls out with), and
the Trainer clips gradients at norm 1 by default (the paper's recipe).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from torch_ampn.training.datamodule import AMPNDataModule
from torch_ampn.training.module import AMPNLightningModule


class AMPNCLI(LightningCLI):
    """LightningCLI with the model -> data links of torch-ampn."""

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        """Link model and data arguments."""
        parser.link_arguments("model.contact_radius", "data.contact_radius")
        parser.link_arguments("model.contact_k", "data.contact_k")
        parser.link_arguments("model.contact_mode", "data.contact_mode")
        parser.link_arguments("model.contact_positions", "data.contact_positions")
        parser.link_arguments("model.num_levels", "data.max_levels")


def main(args: Sequence[str] | None = None, run: bool = True) -> AMPNCLI:
    """Run (or with ``run=False`` only build) the ``torch-ampn`` CLI; returns it."""
    # Rollout items are moved by the rollout itself (see AMPNLightningModule.transfer_batch_to_device).
    warnings.filterwarnings("ignore", message=".*overridden `transfer_batch_to_device`.*")
    return AMPNCLI(
        AMPNLightningModule,
        AMPNDataModule,
        trainer_defaults={"gradient_clip_val": 1.0},
        save_config_kwargs={"overwrite": True},
        args=list(args) if args is not None else None,
        run=run,
    )


def entry_point() -> None:
    """Console script ``torch-ampn``."""
    main()


if __name__ == "__main__":
    entry_point()
