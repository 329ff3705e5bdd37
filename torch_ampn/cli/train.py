"""``torch-ampn``: the Lightning CLI (``fit``, ``validate``, ``test``, ``predict``).

The model is a subclass of :class:`~torch_ampn.training.SurrogateLightningModule`, named by
``model.class_path`` (default :class:`~torch_ampn.training.NextStepLightningModule`; or
``--model DirectLightningModule``), its arguments under ``model.init_args`` (a later config file
or ``--model.NAME`` may give them flat).

    torch-ampn fit --config examples/configs/quickstart.yaml
    torch-ampn test --config examples/configs/quickstart.yaml \
        --ckpt_path outputs/quickstart_nextstep/checkpoints/best.ckpt
    torch-ampn predict --ckpt_path CKPT --data.predict_file examples/predict_settings.yaml

The model's contact settings and level count are linked into the data module (the
training windows are built with the same contact edges the model rolls out with), so is
its kind (``data.mode``), and
the Trainer clips gradients at norm 1 by default (the paper's recipe).

With ``--ckpt_path`` the model's settings come from the checkpoint. Settings given on the
command line or in a config file still win where they do not change the network
(:data:`RUNTIME_OPTIONS`: output folder, XDMF export, rollout seed, baseline radii, compiled
training step); any other given setting that differs from the checkpoint's is refused with
a message, never ignored.
"""

from __future__ import annotations

import copy
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from torch_ampn.training.checkpoint import MODULES, module_arguments, module_class, module_defaults
from torch_ampn.training.datamodule import AMPNDataModule
from torch_ampn.training.module import SurrogateLightningModule
from torch_ampn.training.next_step_module import NextStepLightningModule
from torch_ampn.training.progress import FitProgress
from torch_ampn.utils.io import load_torch_file

#: Options of the Lightning modules that do not change the network: given with
#: ``--ckpt_path``, they win over the checkpoint's values.
RUNTIME_OPTIONS = (
    "output_dir",
    "export_xdmf",
    "rollout_seed",
    "touch_radii",
    "compile_network",
    "fast_rollout",
    "check_mesh",
)


def class_path(module_class: type) -> str:
    """``"package.module.Class"`` of a class, as ``model.class_path`` names it."""
    return f"{module_class.__module__}.{module_class.__name__}"


#: ``model.class_path`` without a config: the seed paper's next-step model.
DEFAULT_CLASS_PATH = class_path(NextStepLightningModule)


def model_of_class_path(path: str) -> str:
    """``data.mode`` of a ``model.class_path``: the model name of the module class it names."""
    for name, klass in MODULES.items():
        if path in (class_path(klass), klass.__name__, f"torch_ampn.training.{klass.__name__}"):
            return name
    return NextStepLightningModule.MODEL


def _same(a: Any, b: Any) -> bool:
    """Equal values, with lists and tuples alike (YAML gives lists, checkpoints may hold tuples)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    return a == b


def _check_checkpoint(subcommand: str, path: str) -> None:
    """Exit with a one-line message unless ``path`` is a readable torch-ampn checkpoint."""
    from torch_ampn.utils.io import load_torch_file

    if not Path(path).is_file():
        sys.exit(f"torch-ampn {subcommand}: {path}: no such checkpoint file")
    try:
        ckpt = load_torch_file(path, "checkpoint")
    except ValueError as err:
        sys.exit(f"torch-ampn {subcommand}: {err}")
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        sys.exit(f"torch-ampn {subcommand}: {path}: not a Lightning checkpoint (no field 'state_dict')")
    hparams = ckpt.get("hyper_parameters") or {}
    if not all(k in hparams for k in ("num_components", "hidden_channels", "num_levels")):
        sys.exit(
            f"torch-ampn {subcommand}: {path}: not a torch-ampn checkpoint "
            "(field 'hyper_parameters' lacks the Lightning module's settings)"
        )


def shortfall(steps: int, planned: int) -> str | None:
    """A ``WARNING`` line if a fit made fewer than ``planned`` steps; ``None`` if not (or none planned)."""
    if planned is None or planned <= 0 or steps >= planned:
        return None
    return (
        f"WARNING: the fit ended after {steps} of its planned {planned} steps "
        f"({100 * steps / planned:.0f} %): its result is not that of the config "
        "(a time limit, an interruption, or a machine slower or busier than planned)"
    )


def _refuse_model_mode(args: list[str]) -> None:
    """Exit in one line where a config file or flag gives ``model.mode`` (a class names the model now)."""
    how = (
        "model.mode is gone: name the module instead (model.class_path: torch_ampn.training."
        "DirectLightningModule or NextStepLightningModule, its arguments under model.init_args)"
    )
    if any(a == "--model.mode" or a.startswith("--model.mode=") for a in args):
        sys.exit(f"torch-ampn: --model.mode: {how}")
    files = [b for a, b in zip(args, args[1:], strict=False) if a in ("--config", "-c")]
    files += [a.split("=", 1)[1] for a in args if a.startswith("--config=")]
    for name in files:
        try:
            config = yaml.safe_load(Path(name).read_text())
        except (OSError, yaml.YAMLError):
            continue  # the parser reports it
        model = config.get("model") if isinstance(config, dict) else None
        if isinstance(model, dict) and "mode" in model:
            sys.exit(f"torch-ampn: {name}: {how}")


class AMPNCLI(LightningCLI):
    """LightningCLI with torch-ampn's model -> data links; checkpoint settings never hide given ones."""

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        """Link model and data arguments."""
        for model_key, data_key in [
            ("contact_radius", "contact_radius"),
            ("contact_k", "contact_k"),
            ("contact_mode", "contact_mode"),
            ("contact_positions", "contact_positions"),  # the next-step model's only
            ("bundle_steps", "bundle_steps"),  # the next-step model's only
            ("num_levels", "max_levels"),
        ]:
            parser.link_arguments(f"model.init_args.{model_key}", f"data.{data_key}")
        parser.link_arguments("model.class_path", "data.mode", compute_fn=model_of_class_path)
        parser.set_defaults({"model": {"class_path": DEFAULT_CLASS_PATH}})
        parser.add_lightning_class_args(FitProgress, "progress")

    def after_fit(self) -> None:
        """One line when the fit ended short of ``trainer.max_steps`` (e.g. at ``max_time``).

        With ``AMPN_REQUIRE_PLANNED_STEPS=1`` (the main job sets it) such a fit exits with status 3.
        """
        message = shortfall(self.trainer.global_step, self.trainer.max_steps)
        if message is None:
            return
        print(message, file=sys.stderr)
        if os.environ.get("AMPN_REQUIRE_PLANNED_STEPS") == "1":
            sys.exit(3)

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        """Parse; with ``--ckpt_path``, check the file and keep the model settings given before it.

        :meth:`_parse_ckpt_path` then replaces the model's settings with the checkpoint's;
        :meth:`before_instantiate_classes` puts the given runtime options back and refuses given
        settings of the trained network.
        """
        _refuse_model_mode(list(sys.argv[1:] if args is None else args))
        super().parse_arguments(parser, args)
        self._given_model = None
        subcommand = self.config.get("subcommand")
        if subcommand and self.config[subcommand].get("ckpt_path"):
            _check_checkpoint(subcommand, self.config[subcommand].ckpt_path)
            self._given_model = copy.deepcopy(self.config[subcommand].model)

    def _parse_ckpt_path(self) -> None:
        """The model of ``--ckpt_path``: its class and settings (also from before the split)."""
        subcommand = self.config.get("subcommand")
        path = self.config[subcommand].get("ckpt_path") if subcommand else None
        if not path or not Path(path).is_file():
            return
        checkpoint = load_torch_file(path, "checkpoint")
        try:
            klass = module_class(checkpoint, path)
        except ValueError as err:
            sys.exit(f"torch-ampn {subcommand}: {err}")
        init_args = module_arguments(checkpoint.get("hyper_parameters") or {}, klass)
        model = {"class_path": class_path(klass), "init_args": init_args}
        self.config = self.parser.parse_object({subcommand: {"model": model}}, self.config)

    def before_instantiate_classes(self) -> None:
        """Given runtime options win over the checkpoint's; other given settings that differ are refused."""
        given = getattr(self, "_given_model", None)
        if given is None:
            return
        subcommand = self.config.subcommand
        model = self.config[subcommand].model
        path = self.config[subcommand].ckpt_path
        given_args = vars(given.get("init_args") or {})
        given_class = given.get("class_path") or DEFAULT_CLASS_PATH
        given_model, saved_model = model_of_class_path(given_class), model_of_class_path(model.class_path)
        defaults = module_defaults(MODULES[given_model])
        if given_model not in (saved_model, NextStepLightningModule.MODEL):  # the default model: no config
            sys.exit(
                f"torch-ampn {subcommand}: {path}: holds a {model.class_path.rsplit('.', 1)[-1]}, "
                f"not the {given_class.rsplit('.', 1)[-1]} of the given config; give the config the "
                "checkpoint was trained with, or none"
            )
        accepted = module_defaults(MODULES[saved_model])
        conflicts = []
        for key, value in given_args.items():
            if _same(value, defaults.get(key)) or _same(value, model.init_args.get(key)):
                continue
            if key not in accepted:
                conflicts.append(f"model.{key}={value!r} (not an argument of the checkpoint's model)")
            elif key in RUNTIME_OPTIONS:
                model.init_args[key] = value
            else:
                conflicts.append(f"model.{key}={value!r} (the checkpoint has {model.init_args.get(key)!r})")
        if conflicts:
            sys.exit(
                f"torch-ampn {subcommand}: {path}: "
                f"{', '.join(conflicts)}: these settings belong to the trained model and cannot be "
                "changed with --ckpt_path; drop them (or train a new model)"
            )


def main(args: Sequence[str] | None = None, run: bool = True) -> AMPNCLI:
    """Run (or with ``run=False`` only build) the ``torch-ampn`` CLI; returns it."""
    # Rollout items are moved by the rollout itself (see SurrogateLightningModule.transfer_batch_to_device).
    warnings.filterwarnings("ignore", message=".*overridden `transfer_batch_to_device`.*")
    # configure_model only fits the normalisation statistics (no sharded layers; see the module's hook)
    warnings.filterwarnings("ignore", message=".*overrides the configure_model callback.*")
    return AMPNCLI(
        SurrogateLightningModule,
        AMPNDataModule,
        subclass_mode_model=True,
        trainer_defaults={"gradient_clip_val": 1.0},
        save_config_kwargs={"overwrite": True},
        args=list(args) if args is not None else None,
        run=run,
    )


def entry_point() -> None:
    """Console script ``torch-ampn``: input errors end in one line on stderr (exit status 1), no traceback.

    ``torch-ampn design ...`` runs :mod:`torch_ampn.cli.design`, ``torch-ampn export ...``
    :mod:`torch_ampn.cli.export`; everything else is the Lightning CLI.

    ``AMPN_TRACEBACK=1`` shows the traceback instead.
    """
    from torch_ampn.data.trajectory import TrajectoryFormatError
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # a program of its own: threads follow the free CPU (a library call leaves them)
    try:
        if sys.argv[1:2] == ["design"]:  # the design study is not a Lightning subcommand
            from torch_ampn.cli.design import main as design

            design(sys.argv[2:])
        elif sys.argv[1:2] == ["export"]:  # nor the model file
            from torch_ampn.cli.export import main as export

            export(sys.argv[2:])
        else:
            main()
    except (ValueError, FileNotFoundError, PermissionError, TrajectoryFormatError) as err:
        if os.environ.get("AMPN_TRACEBACK"):
            raise
        sys.exit(f"torch-ampn: error: {' '.join(str(err).split())}")


if __name__ == "__main__":
    entry_point()
