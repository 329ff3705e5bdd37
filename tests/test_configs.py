"""The example configs parse and instantiate through the ``torch-ampn`` CLI, with the values they set.

No training and no data: ``main(..., run=False)`` only builds the model, the data module and the
Trainer (on the CPU; paper.yaml asks for a GPU). The expected values are read from the YAML
files, so the test follows edits of the configs; the paper's architecture is also checked by
its numbers (d = 128, 15 layers, 4 levels, k = 3).
"""

from pathlib import Path

import pytest
import yaml

pytest.importorskip("lightning")

from helpers import checkpoint_steps  # noqa: E402
from lightning.pytorch.callbacks import ModelCheckpoint  # noqa: E402

from torch_ampn.cli.train import main  # noqa: E402
from torch_ampn.training import (  # noqa: E402
    AMPNDataModule,
    DirectLightningModule,
    NextStepLightningModule,
    SurrogateLightningModule,
)

CONFIGS = Path(__file__).resolve().parents[1] / "examples" / "configs"
NAMES = [
    "quickstart.yaml",
    "paper.yaml",
    "family.yaml",
    "settings.yaml",
    "settings_prior.yaml",
    "direct.yaml",
]


def _build(name, tmp_path, monkeypatch):
    """The CLI of ``examples/configs/<name>``, built in ``tmp_path`` (relative paths land there)."""
    monkeypatch.chdir(tmp_path)
    cli = main(["--config", str(CONFIGS / name), "--trainer.accelerator", "cpu"], run=False)
    return cli, yaml.safe_load((CONFIGS / name).read_text())


def model_args(config: dict) -> dict:
    """A config's model arguments: ``model.init_args`` (a first config) or ``model`` (an overlay)."""
    return config["model"].get("init_args", {k: v for k, v in config["model"].items() if k != "class_path"})


def _same(a, b):
    """Equal, floats up to rounding (YAML's ``1.0e-4`` vs the parsed value)."""
    if isinstance(b, float) and not isinstance(a, bool):
        return a == pytest.approx(b)
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("name", NAMES)
def test_config_builds_model_data_and_trainer(name, tmp_path, monkeypatch):
    cli, config = _build(name, tmp_path, monkeypatch)
    model, dm, trainer = cli.model, cli.datamodule, cli.trainer
    assert isinstance(model, SurrogateLightningModule) and isinstance(dm, AMPNDataModule)
    assert type(model).__name__ == config["model"]["class_path"].rsplit(".", 1)[1]

    # every model and data value of the YAML reaches the instantiated modules
    for key, value in model_args(config).items():
        assert _same(model.hparams[key], value), f"model.{key}: {model.hparams[key]!r} != {value!r}"
    for key, value in config["data"].items():
        assert _same(dm.hparams[key], value), f"data.{key}: {dm.hparams[key]!r} != {value!r}"

    # ... and the network built from them
    hp, surrogate = model.hparams, model.surrogate
    net = surrogate.model
    assert net.hidden_channels == hp.hidden_channels
    assert net.mlp_channels == hp.mlp_channels
    assert net.num_levels == surrogate.num_levels == hp.num_levels
    layers = [hp[f"{s}_layers"] for s in ("pre", "down", "solve", "post", "up")]
    assert [len(s) for s in (net.pre, net.down, net.solve, net.post, net.up)] == layers
    assert net.num_layers == sum(layers)
    assert surrogate.contact.k == hp.contact_k and surrogate.contact.r == hp.contact_radius
    if isinstance(
        model, DirectLightningModule
    ):  # the data module yields whole trajectories for it (the CLI's link)
        assert type(surrogate).__name__ == "DirectSurrogate" and dm.hparams.mode == "direct"
    else:
        assert isinstance(model, NextStepLightningModule)
        assert surrogate.diffusion_steps == hp.diffusion_steps == 1
        assert model._compiled_network is (
            None if hp.compile_network else False
        )  # compiles at the first step
        assert dm.hparams.mode == "next_step"

    # the CLI links the model's contact settings and level count into the data module
    assert dm.hparams.contact_k == hp.contact_k and dm.hparams.contact_radius == hp.contact_radius
    assert dm.contact.k == hp.contact_k and dm.contact.r == hp.contact_radius
    assert dm.hparams.max_levels == hp.num_levels

    # the Trainer: the config's limits, the CLI's clipping default, the config's callbacks
    t = config["trainer"]
    assert trainer.max_steps == t["max_steps"]
    assert trainer.val_check_interval == t["val_check_interval"]
    assert trainer.gradient_clip_val == 1.0
    logger_class = t["logger"]["class_path"].rsplit(".", 1)[1]
    assert type(trainer.logger).__name__ == logger_class
    callbacks = {type(c).__name__ for c in trainer.callbacks}
    assert {c["class_path"].rsplit(".", 1)[1] for c in t["callbacks"]} <= callbacks
    assert trainer.checkpoint_callback.monitor == "val/rollout_rmse"

    # building touched nothing: no data generated, no output folders
    assert not (tmp_path / dm.hparams.data_dir).exists()
    assert not (tmp_path / "outputs").exists()


def test_paper_config_has_the_papers_network(tmp_path, monkeypatch):
    cli, config = _build("paper.yaml", tmp_path, monkeypatch)
    assert config["trainer"]["accelerator"] == "gpu"  # replaced by cpu above
    net = cli.model.surrogate.model
    assert (net.hidden_channels, net.mlp_channels) == (128, 128)
    assert net.num_layers == 15 and net.num_levels == 4
    assert cli.model.surrogate.contact.k == 3 and cli.model.surrogate.contact.r == 3.0
    assert cli.datamodule.hparams.resolution == "paper" and cli.datamodule.hparams.batch_size == 1


def test_quickstart_config_is_smaller_than_the_papers(tmp_path, monkeypatch):
    quick, _ = _build("quickstart.yaml", tmp_path, monkeypatch)
    paper, _ = _build("paper.yaml", tmp_path, monkeypatch)
    count = lambda cli: sum(p.numel() for p in cli.model.parameters())  # noqa: E731
    assert count(quick) < count(paper)
    assert quick.trainer.accelerator.__class__.__name__ == "CPUAccelerator"


@pytest.mark.parametrize("name", NAMES)
def test_config_checkpoints_keep_the_best_and_the_last_step(name, tmp_path, monkeypatch):
    """``last.ckpt`` follows every validation (to resume from), ``best.ckpt`` the lowest RMSE,
    also when validation gets worse (Lightning's ``save_last`` alone would keep step 2 in both)."""
    cli, _ = _build(name, tmp_path, monkeypatch)
    checkpoints = [c for c in cli.trainer.callbacks if isinstance(c, ModelCheckpoint)]
    folders = {Path(c.dirpath) for c in checkpoints}
    assert len(folders) == 1
    assert checkpoint_steps(checkpoints, folders.pop()) == (2, 6)


def test_lightning_save_last_alone_lags_behind(tmp_path):
    """Why the configs carry a checkpoint of their own for ``last.ckpt``: if this starts failing,
    Lightning's ``save_last`` follows every validation again and the second callback can go."""
    callback = ModelCheckpoint(tmp_path, "best", monitor="val/rollout_rmse", save_last=True)
    assert checkpoint_steps([callback], tmp_path) == (2, 2)


def test_the_main_jobs_configs_are_the_direct_model_without_message_passing(tmp_path, monkeypatch):
    """scripts/quickstart.sh: direct.yaml, then quickstart_direct.yaml on top of it."""
    from torch_geometric.nn import MessagePassing

    monkeypatch.chdir(tmp_path)
    names = ["direct.yaml", "quickstart_direct.yaml"]
    cli = main([a for name in names for a in ("--config", str(CONFIGS / name))], run=False)
    direct, extra = (yaml.safe_load((CONFIGS / name).read_text()) for name in names)
    hp = cli.model.hparams
    assert isinstance(cli.model, DirectLightningModule) and hp.num_levels == 1
    assert hp.pre_layers == hp.solve_layers == hp.post_layers == 0
    assert cli.model.surrogate.target_scale == "step"
    assert not any(isinstance(m, MessagePassing) for m in cli.model.surrogate.modules())
    for key in ("hidden_channels", "decoder_modes", "base", "lr", "loss_steps"):
        assert hp[key] == model_args(direct)[key]  # the rest is direct.yaml's
    assert cli.trainer.max_steps == extra["trainer"]["max_steps"]
    assert cli.datamodule.hparams.num_train == direct["data"]["num_train"]
    # everything it writes lands in outputs/quickstart, as the job says
    checkpoints = [c for c in cli.trainer.callbacks if isinstance(c, ModelCheckpoint)]
    assert {Path(c.dirpath) for c in checkpoints} == {tmp_path / "outputs/quickstart/checkpoints"}
    assert hp.output_dir == "outputs/quickstart" and cli.trainer.default_root_dir == "outputs/quickstart"


def test_the_prior_recipe_adds_the_prior_to_the_quickstart(tmp_path, monkeypatch):
    """The next-step recipe with the POD + GP prior: quickstart.yaml, then quickstart_prior.yaml."""
    monkeypatch.chdir(tmp_path)
    names = ["quickstart.yaml", "quickstart_prior.yaml"]
    args = [a for name in names for a in ("--config", str(CONFIGS / name))]
    cli = main(args, run=False)
    quick, extra = (yaml.safe_load((CONFIGS / name).read_text()) for name in names)
    hp, dm = cli.model.hparams, cli.datamodule
    assert hp.prior_features is True and hp.compile_network is False and dm.hparams.prior == "pod_gp"
    assert hp.fast_rollout is False  # as the published result: nothing compiled after the fit
    assert cli.model.surrogate.prior_features
    assert cli.trainer.max_steps == extra["trainer"]["max_steps"]
    for key in ("hidden_channels", "num_levels", "contact_k", "pushforward"):
        assert hp[key] == model_args(quick)[key]  # the rest is the quickstart's
    assert dm.hparams.num_train == quick["data"]["num_train"]


#: Every public recipe: a config and the overlays given after it.
RECIPES = [[name] for name in NAMES] + [
    ["quickstart.yaml", "quickstart_prior.yaml"],
    ["direct.yaml", "quickstart_direct.yaml"],
]


def test_no_two_recipes_write_to_the_same_folder(tmp_path, monkeypatch):
    """A recipe's checkpoints, logs and reports never overwrite another's (the version counter is off)."""
    monkeypatch.chdir(tmp_path)
    seen: dict[str, str] = {}
    for recipe in RECIPES:
        args = [a for name in recipe for a in ("--config", str(CONFIGS / name))]
        cli = main([*args, "--trainer.accelerator", "cpu"], run=False)
        checkpoints = {str(c.dirpath) for c in cli.trainer.callbacks if isinstance(c, ModelCheckpoint)}
        folders = {*checkpoints, str(cli.trainer.default_root_dir), str(cli.model.hparams.output_dir)}
        for folder in folders:
            other = seen.setdefault(folder, " + ".join(recipe))
            assert other == " + ".join(recipe), f"{folder}: written by {other} and by {' + '.join(recipe)}"
