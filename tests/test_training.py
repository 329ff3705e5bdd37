"""Lightning module, data module, LR schedule, checkpoints and the torch-ampn CLI on a tiny dataset."""

import csv
import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

pytest.importorskip("lightning")

import helpers  # noqa: E402
import lightning as L  # noqa: E402
from make_fixtures import SMALL_MODEL, TINY_CKPT, fit_config  # noqa: E402
from torch_geometric.data import Batch  # noqa: E402

from torch_ampn.cli.train import main  # noqa: E402
from torch_ampn.data import NodeType, Trajectory, step_sample  # noqa: E402
from torch_ampn.rollout import rollout_rmse  # noqa: E402
from torch_ampn.sim import StampFormingConfig, generate_dataset, simulate_batch  # noqa: E402
from torch_ampn.sim.config import MATERIAL_V1, PHYSICS_V2  # noqa: E402
from torch_ampn.testing import SMALL_SIMULATOR  # noqa: E402
from torch_ampn.training import (  # noqa: E402
    AMPNDataModule,
    NextStepLightningModule,
    WarmupExponentialDecay,
    warmup_exponential_decay,
)


@pytest.fixture(scope="module")
def data_dir(tiny_data):
    """The committed tiny dataset (2/1/1 trajectories of ``small_sim``), a copy of the run's."""
    return tiny_data


def _datamodule(data_dir, **kwargs):
    dm = AMPNDataModule(str(data_dir), generate=False, max_levels=2, min_coarse_nodes=4, **kwargs)
    dm.setup("fit")
    return dm


def _quiet_trainer(max_steps, callbacks=None):
    """A CPU trainer without logger, checkpoints, progress bar or validation."""
    return L.Trainer(
        max_steps=max_steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        accelerator="cpu",
        callbacks=callbacks,
    )


def _fitted_module(data_dir, **kwargs):
    module = NextStepLightningModule(**SMALL_MODEL, **kwargs)
    dm = _datamodule(data_dir)
    module.fit_statistics(dm.statistics_samples(8))
    return module, dm


# ---- schedule ---------------------------------------------------------------------------------
def test_schedule_formula_at_chosen_steps():
    lr, final, warm, total = 1e-4, 1e-5, 10, 110
    f = lambda s: warmup_exponential_decay(s, warm, total, lr, final)  # noqa: E731
    assert f(0) == pytest.approx(1 / 10) and f(4) == pytest.approx(5 / 10) and f(9) == pytest.approx(1.0)
    assert f(10) == pytest.approx(1.0)  # decay starts at lr
    assert lr * f(60) == pytest.approx(math.sqrt(lr * final))  # half-way: geometric mean
    assert lr * f(110) == pytest.approx(final) and lr * f(500) == pytest.approx(final)
    assert warmup_exponential_decay(3, 0, 10, 1.0, 0.1) == pytest.approx(0.1**0.3)
    with pytest.raises(ValueError):
        warmup_exponential_decay(0, 1, 10, 0.0, 1e-5)


class _FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_schedule_without_time_budget_is_the_step_formula():
    f = WarmupExponentialDecay(10, 110, 1e-4, 1e-5)
    assert [f(s) for s in range(0, 200, 7)] == [
        warmup_exponential_decay(s, 10, 110, 1e-4, 1e-5) for s in range(0, 200, 7)
    ]
    g = WarmupExponentialDecay(10, 110, 1e-4, 1e-5, time_remaining=lambda: None)  # Timer without max_time
    assert [g(s) for s in range(0, 200, 7)] == [f(s) for s in range(0, 200, 7)]


def test_schedule_under_a_time_budget_decays_with_whichever_runs_out_first():
    clock = _FakeClock()
    remaining = {"s": 1000.0}
    f = WarmupExponentialDecay(10, 110, 1e-4, 1e-5, time_remaining=lambda: remaining["s"], clock=clock)
    # warm-up counts steps only, however much time passes
    clock.now += 5000.0
    assert f(0) == pytest.approx(0.1) and f(9) == pytest.approx(1.0)
    # the first decay step notes the time left (R_0 = 400 s) and starts at lr
    remaining["s"] = 400.0
    assert f(10) == pytest.approx(1.0)
    # 100 s later (a quarter of R_0) at step 20 (a tenth of the steps): time leads, p = 1/4
    clock.now += 100.0
    assert 1e-4 * f(20) == pytest.approx(1e-4 * 0.1**0.25)
    # at step 85 (p_steps = 3/4 > 1/4) the steps lead
    assert 1e-4 * f(85) == pytest.approx(1e-4 * 0.1**0.75)
    # when the budget is spent the rate is final_lr, and stays there
    clock.now += 300.0
    assert 1e-4 * f(30) == pytest.approx(1e-5)
    clock.now += 300.0
    assert 1e-4 * f(31) == pytest.approx(1e-5)
    # a budget already spent at the first decay step: final_lr at once
    h = WarmupExponentialDecay(0, 10, 1.0, 0.1, time_remaining=lambda: 0.0, clock=clock)
    assert h(0) == pytest.approx(0.1)


def test_time_limited_fit_ends_at_the_final_rate_with_a_validation(data_dir, tmp_path):
    """trainer.max_time stops a fit long before max_steps; the rate has decayed to final_lr by then."""
    torch.manual_seed(0)
    module = NextStepLightningModule(
        **SMALL_MODEL, lr=1e-3, final_lr=1e-4, warmup_steps=2, statistics_samples=8
    )
    dm = AMPNDataModule(str(data_dir), generate=False, max_levels=2, min_coarse_nodes=4)
    lrs, vals = [], []

    class Record(L.Callback):
        def on_train_batch_end(self, trainer, *args):
            lrs.append(trainer.optimizers[0].param_groups[0]["lr"])

        def on_validation_end(self, trainer, *args):
            vals.append(trainer.global_step)

    trainer = L.Trainer(
        max_steps=100_000,
        max_time={"seconds": 3},
        val_check_interval=100_000,
        check_val_every_n_epoch=None,
        logger=False,
        default_root_dir=str(tmp_path),
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        accelerator="cpu",
        callbacks=[Record(), L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)],
    )
    trainer.fit(module, dm)
    steps = trainer.global_step
    assert 3 < steps < 100_000
    # the step formula alone would still be at the peak rate; the time budget brought it to final_lr
    assert 1e-3 * warmup_exponential_decay(steps, 2, 100_000, 1e-3, 1e-4) > 9e-4
    assert lrs[-1] == pytest.approx(1e-4, rel=1e-6)
    assert all(
        a >= b - 1e-12 for a, b in zip(lrs[2:-1], lrs[3:], strict=True)
    )  # decays monotonically after warm-up
    assert vals and vals[-1] == steps  # validation runs at the stop, so the last weights are checked
    # the checkpoint loads weights-only (as `torch-ampn test --ckpt_path` does): no clock or Timer inside
    ckpt = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == steps


def test_module_scheduler_steps_per_optimiser_step(data_dir, monkeypatch):
    module = NextStepLightningModule(**SMALL_MODEL, lr=1e-3, final_lr=1e-4, warmup_steps=4)
    monkeypatch.setattr(module, "_total_steps", lambda: 24)
    conf = module.configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert conf["lr_scheduler"]["interval"] == "step"
    lrs = []
    for _ in range(30):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    expected = [1e-3 * (s + 1) / 4 if s < 4 else 1e-3 * 0.1 ** (min(s - 4, 20) / 20) for s in range(30)]
    assert lrs == pytest.approx(expected, rel=1e-9)


# ---- training ----------------------------------------------------------------------------------
def test_one_training_step_lowers_the_loss_on_a_fixed_batch(data_dir):
    torch.manual_seed(0)
    module, dm = _fitted_module(data_dir, position_noise=0.0, residual_noise=0.0)
    batch = next(iter(dm.train_dataloader()))
    opt = torch.optim.Adam(module.parameters(), lr=1e-3)

    def loss():
        torch.manual_seed(1)  # the same N(0, 1) noise input every time
        return module.training_step(batch, 0)

    module.log = lambda *a, **k: None  # no trainer attached
    before = loss()
    before.backward()
    opt.step()
    with torch.no_grad():
        after = loss()
    assert float(after) < float(before)


def test_normalisation_statistics_come_from_training_windows_only(data_dir):
    module, dm = _fitted_module(data_dir)
    s = module.surrogate
    assert s.statistics_frozen
    windows = list(dm.statistics_samples(8))
    targets = torch.cat([w["l0"].target[w["l0"].ply_mask] for w in windows]).double()
    torch.testing.assert_close(s.target_norm.mean, targets.mean(0))
    torch.testing.assert_close(s.target_norm.std, targets.std(0, unbiased=False))
    positions = torch.cat([w["l0"].pos for w in windows]).double()
    assert s.position_std == pytest.approx(float(positions.std(0, unbiased=False).mean()))
    with pytest.raises(RuntimeError, match="frozen"):
        s.accumulate_statistics(windows[0])


def test_training_noise_has_the_requested_size_on_plies_only(data_dir):
    module, dm = _fitted_module(data_dir, position_noise=1e-2, residual_noise=1e-3)
    window = dm.train_dataset[3]
    clean_pos, clean_prev = window["l0"].pos.clone(), window["l0"].prev_disp.clone()
    clean_target = window["l0"].target.clone()
    torch.manual_seed(0)
    noisy = module.add_training_noise(window)
    ply = noisy["l0"].ply_mask
    sigma = module.surrogate.position_std
    dpos = noisy["l0"].pos - clean_pos
    dprev = noisy["l0"].prev_disp - clean_prev
    assert torch.equal(dpos[~ply], torch.zeros_like(dpos[~ply]))  # tools never get noise
    assert torch.equal(dprev[~ply], torch.zeros_like(dprev[~ply]))
    assert float(dpos[ply].std()) == pytest.approx(1e-2 * sigma, rel=0.15)
    assert float(dprev[ply].std()) == pytest.approx(1e-3 * sigma, rel=0.15)
    # the target still leads to the true next position: (x^{t-1} + eps) + target' = x^t
    torch.testing.assert_close(noisy["l0"].pos + noisy["l0"].target, clean_pos + clean_target)


def test_correlated_noise_is_a_consistent_position_error(data_dir):
    """With correlated noise the noisy window is the one a rollout with a wrong x^{t-1} sees."""
    module, dm = _fitted_module(data_dir, position_noise=1e-2, residual_noise=0.0, correlated_noise=True)
    index = 5
    window = dm.train_dataset[index]
    j, t = dm.train_dataset.index(index)
    traj = dm.train_dataset.trajectories[j]
    assert t >= 2
    torch.manual_seed(0)
    noisy = module.add_training_noise(window)["l0"]
    ply = noisy.ply_mask
    eps = noisy.pos - traj.pos[t - 1]
    assert torch.equal(eps[~ply], torch.zeros_like(eps[~ply]))
    assert float(eps[ply].std()) == pytest.approx(1e-2 * module.surrogate.position_std, rel=0.15)
    # the previous residual is measured from the noisy position: x^{t-1} + eps - x^{t-2}
    torch.testing.assert_close(noisy.pos - noisy.prev_disp, traj.pos[t - 2])
    # and the target still leads to the true x^t
    torch.testing.assert_close(noisy.pos + noisy.target, traj.pos[t])
    # residual noise comes on top, independently
    module, _ = _fitted_module(data_dir, position_noise=1e-2, residual_noise=1e-3, correlated_noise=True)
    torch.manual_seed(0)
    noisy = module.add_training_noise(dm.train_dataset[index])["l0"]
    extra = noisy.prev_disp - (noisy.pos - traj.pos[t - 2])
    assert float(extra[ply].std()) == pytest.approx(1e-3 * module.surrogate.position_std, rel=0.15)


def test_pushforward_starts_from_the_models_own_prediction(data_dir):
    """The window (t-2, t-1) rebuilt from a window's fields is step_sample's; its prediction moves x^{t-1}."""
    module, dm = _fitted_module(data_dir, pushforward=1.0)
    dataset = dm.train_dataset
    first, later = 0, 5  # windows at t = 1 (nothing to push forward) and t = 6
    j, t = dataset.index(later)
    assert dataset.index(first)[1] == 1 and t >= 3
    traj = dataset.trajectories[j]
    window = dataset[later]
    # reference: the window (t-2, t-1) made from the trajectory, with window t's contact edges
    prior = step_sample(traj, t - 1, dataset.hierarchies(traj))
    prior.traj_index = window.traj_index
    for key in window.edge_types:
        if key[1] == "contact":
            prior[key].edge_index = window[key].edge_index
    torch.manual_seed(3)
    with torch.no_grad():
        reference = module.surrogate.predict_residual(Batch.from_data_list([dataset[first], prior]))
    batch = Batch.from_data_list([dataset[first], window])
    clean = batch["l0"].pos.clone(), batch["l0"].prev_disp.clone(), batch["l0"].target.clone()
    torch.manual_seed(3)
    pushed = module.pushforward_inputs(batch)["l0"]
    ply, in_later = pushed.ply_mask, pushed.batch == 1
    error = (reference - clean[1]) * (ply & in_later)[:, None]  # the model's error of du^{t-1}
    assert float(error.abs().max()) > 0
    torch.testing.assert_close(pushed.pos, clean[0] + error)
    torch.testing.assert_close(pushed.prev_disp, clean[1] + error)
    torch.testing.assert_close(pushed.target, clean[2] - error)
    # still consistent with the trajectory: x^{t-2} behind, x^t ahead
    torch.testing.assert_close(pushed.pos[in_later] - pushed.prev_disp[in_later], traj.pos[t - 2])
    torch.testing.assert_close(pushed.pos[in_later] + pushed.target[in_later], traj.pos[t])
    with pytest.raises(ValueError, match="pushforward"):
        NextStepLightningModule(**SMALL_MODEL, pushforward=1.5)


def test_robin_mode_trains_and_samples(data_dir):
    torch.manual_seed(0)
    module, dm = _fitted_module(data_dir, diffusion_steps=5)
    module.log = lambda *a, **k: None
    batch = next(iter(dm.train_dataloader()))
    loss = module.training_step(batch, 0)
    loss.backward()
    assert torch.isfinite(loss)
    item = dm._rollout_split("val")[0]
    a, _ = module.rollout_item(item)
    b, _ = module.rollout_item(item)
    assert torch.equal(a, b)  # the rollout seed makes K-step sampling reproducible
    assert a.shape == item.trajectory.pos.shape and torch.isfinite(a).all()


def test_checkpoint_round_trip_gives_identical_rollouts(data_dir, tmp_path):
    module, dm = _fitted_module(data_dir)
    trainer = _quiet_trainer(max_steps=2)
    trainer.fit(module, datamodule=dm)
    path = tmp_path / "model.ckpt"
    trainer.save_checkpoint(path)
    restored = NextStepLightningModule.load_from_checkpoint(path)
    assert restored.surrogate.statistics_frozen
    for name, value in module.surrogate.state_dict().items():
        assert torch.equal(value, restored.surrogate.state_dict()[name]), name
    item = dm._rollout_split("val")[0]
    a, _ = module.rollout_item(item)
    b, _ = restored.rollout_item(item)
    assert torch.equal(a, b)
    tools = item.trajectory.node_type != NodeType.PLY
    assert torch.equal(a[:, tools], item.trajectory.pos[:, tools])


def test_datamodule_checks_model_and_predict_settings(data_dir, tmp_path):
    dm = _datamodule(data_dir)
    with pytest.raises(ValueError, match="num_components=5"):
        dm.check_model(NextStepLightningModule(**{**SMALL_MODEL, "num_components": 5}).surrogate)
    with pytest.raises(ValueError, match="num_levels=4"):
        dm.check_model(NextStepLightningModule(**{**SMALL_MODEL, "num_levels": 4}).surrogate)
    with pytest.raises(ValueError, match="predict needs process settings"):
        dm.predict_settings()
    bad = tmp_path / "settings.json"
    bad.write_text(json.dumps([{"gripper_positions": [0.5, 0.5]}]))
    dm = AMPNDataModule(str(data_dir), generate=False, predict_file=str(bad))
    with pytest.raises(ValueError, match=f"{bad}: setting 0 lacks field 'gripper_forces'"):
        dm.predict_settings()
    with pytest.raises(FileNotFoundError, match="no trajectories"):
        AMPNDataModule(str(tmp_path / "empty"), generate=False).prepare_data()
    with pytest.raises(ValueError, match="data.simulator"):
        AMPNDataModule(str(tmp_path / "x"), simulator={"ply_cells": -3}).prepare_data()


def copy_splits_of(source):
    """A dataset maker (``make_dataset``) that copies the first trajectories of each split of ``source``."""
    import shutil

    def make(folder, num_train, num_val, num_test):
        for split, count in (("train", num_train), ("val", num_val), ("test", num_test)):
            (folder / split).mkdir(parents=True, exist_ok=True)
            for path in sorted((source / split).glob("*.pt"))[:count]:
                shutil.copy(path, folder / split / path.name)

    return make


#: A dataset maker named by its import path, as a config gives it (set by the test below).
named_maker = None


def test_datamodule_takes_a_dataset_maker(tmp_path, tiny_data):
    made = []

    def maker(folder, num_train, num_val, num_test):
        made.append((folder, num_train, num_val, num_test))
        copy_splits_of(tiny_data)(folder, num_train, num_val, num_test)

    dm = AMPNDataModule(str(tmp_path / "own"), num_train=2, num_val=1, num_test=0, make_dataset=maker)
    dm.prepare_data()  # the maker, not the simulator
    assert made == [(tmp_path / "own", 2, 1, 0)]
    assert (
        sorted(p.name for p in (tmp_path / "own" / "train").glob("*.pt"))
        == sorted(p.name for p in (tiny_data / "train").glob("*.pt"))[:2]
    )
    assert "make_dataset" not in dm.hparams  # a function is no checkpoint value
    dm.setup("fit")
    assert len(dm.train_dataset) > 0
    global named_maker
    named_maker = copy_splits_of(tiny_data)
    by_name = AMPNDataModule(str(tmp_path / "named"), 1, 0, 0, make_dataset="test_training:named_maker")
    by_name.prepare_data()
    assert len(list((tmp_path / "named" / "train").glob("*.pt"))) == 1
    assert by_name.hparams.make_dataset == "test_training:named_maker"
    with pytest.raises(ValueError, match="^data.make_dataset: cannot import 'no_such_module'"):
        AMPNDataModule(str(tmp_path / "x"), make_dataset="no_such_module:make")


def test_datamodule_generates_an_empty_folder(tmp_path):
    dm = AMPNDataModule(
        str(tmp_path / "new"),
        num_train=1,
        num_val=0,
        num_test=0,
        simulator=SMALL_SIMULATOR,
        generate_workers=1,
    )
    dm.prepare_data()
    files = sorted((tmp_path / "new" / "train").glob("*.pt"))
    assert [f.name for f in files] == ["traj_000000.pt"]
    assert dm.simulator_config().ply_cells == 5


# ---- the CLI -----------------------------------------------------------------------------------
def _from_checkpoint(subcommand, ckpt, data_dir, out, *extra):
    """Arguments of ``torch-ampn test`` / ``predict`` that take everything else from ``ckpt``."""
    args = ["--ckpt_path", str(ckpt), "--data.data_dir", str(data_dir), "--data.generate", "false"]
    args += ["--data.min_coarse_nodes", "4"]
    args += ["--model.output_dir", str(out / "reports"), "--trainer.default_root_dir", str(out)]
    return [subcommand, *args, *extra]  # given later, ``extra`` wins


@pytest.mark.slow
def test_test_and_predict_refuse_another_mesh_unless_told(data_dir, tmp_path, small_sim):
    """A checkpoint records its training meshes; test/predict on another mesh stop with the file's name."""
    out, ckpt = tmp_path / "out", TINY_CKPT
    meshes = torch.load(ckpt, weights_only=True)["training_meshes"]
    assert list(meshes.values()) == [Trajectory.load(next((data_dir / "train").glob("*.pt"))).num_nodes]

    other = tmp_path / "other"  # the same components and grippers on a finer mesh
    finer = StampFormingConfig.from_dict({**small_sim.to_dict(), "ply_cells": small_sim.ply_cells + 1})
    generate_dataset(other, 0, 0, 1, config=finer, workers=1, compile=False, progress=False)
    first = sorted((other / "test").glob("*.pt"))[0]
    with pytest.raises(ValueError, match=f"{first}: its mesh .* is not one the model was trained on"):
        main(_from_checkpoint("test", ckpt, other, out))
    with pytest.raises(ValueError, match=f"{other / 'dataset.json'}: the simulator settings make mesh"):
        main(_from_checkpoint("predict", ckpt, other, out, "--data.predict_gripper_positions", "[[0.5, 0.5]]",
                              "--data.predict_gripper_forces", "[[10, 10]]"))  # fmt: skip
    main(_from_checkpoint("test", ckpt, other, out, "--model.check_mesh", "false"))  # told: it runs
    assert any((out / "reports").rglob("test_summary.json"))
    main(_from_checkpoint("test", ckpt, data_dir, out))  # its own mesh: no complaint


@pytest.mark.slow
def test_a_model_of_a_family_of_parts_fits_and_tests_per_part(tmp_path, tiny_family, capsys):
    """Mixed parts (2 and 3 plies: two meshes) in training batches, validation and test; a part column."""
    data = tiny_family
    plies = {len(Trajectory.load(f).meta["part"]["ply_angles"]) for f in sorted(data.glob("*/*.pt"))}
    assert plies == {2, 3}  # both stacks are there
    config, out = fit_config(tmp_path, data)
    settings = yaml.safe_load(config.read_text())
    settings["model"].update(component_encoding="stack", num_components=5)
    settings["data"].update(batch_size=3)
    config.write_text(yaml.safe_dump(settings))
    main(["fit", "--config", str(config)])
    capsys.readouterr()
    main(_from_checkpoint("test", out / "ckpt" / "last.ckpt", data, out))
    printed = capsys.readouterr().out
    rows = list(csv.DictReader(open(next((out / "reports").rglob("test_rmse.csv")))))
    assert len(rows) == 2 and all(r["part"].endswith(" mm") and "plies" in r["part"] for r in rows)
    assert all(math.isfinite(float(r["model"])) for r in rows)
    assert rows[0]["part"] in printed  # the printed table names the parts
    with pytest.raises(ValueError, match="model.num_components=4 but the trajectories .* have up to 5"):
        main(["fit", "--config", str(config), "--model.num_components", "4"])


@pytest.mark.xdist_group("tiny_fit")
def test_cli_fit_test_predict_end_to_end(tiny_fit, tmp_path, capsys):
    data_dir, out = tiny_fit  # the run's one fit: `torch-ampn fit --config` of make_fixtures.fit_config
    ckpt = out / "ckpt" / "last.ckpt"
    assert ckpt.is_file()

    # the LR logged at every optimiser step follows the schedule (6 steps, warm-up 2)
    with open(out / "logs" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("lr-Adam")]
    logged = {int(r["step"]): float(r["lr-Adam"]) for r in rows}
    for step, lr in logged.items():
        assert lr == pytest.approx(1e-3 * warmup_exponential_decay(step, 2, 6, 1e-3, 1e-4), rel=1e-6)
    assert len(logged) >= 5
    assert any(r.get("val/rollout_rmse") for r in csv.DictReader(open(out / "logs" / "metrics.csv")))

    # test needs only the checkpoint (+ where the data is): hyper-parameters come from it
    capsys.readouterr()
    main(_from_checkpoint("test", ckpt, data_dir, out))
    printed = capsys.readouterr().out
    assert "best trivial baseline" in printed and "traj_200000" in printed
    reports = out / "reports"
    with open(reports / "test_rmse.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["trajectory"] for r in rows] == ["traj_200000"]
    assert {"model", "static", "rigid_r3", "rollout_seconds"} <= set(rows[0])
    summary = json.loads((reports / "test_summary.json").read_text())
    # the summary is the mean of the CSV rows, the baseline the best of the baseline columns
    baselines = {k: [float(r[k]) for r in rows] for k in rows[0] if k == "static" or k.startswith("rigid_r")}
    means = {k: sum(v) / len(v) for k, v in baselines.items()}
    assert len(means) == 5  # static and the four touch radii of the default module
    assert summary["baseline_rmse"] == pytest.approx(min(means.values()), rel=1e-5)
    assert summary["static_rmse"] == pytest.approx(means["static"], rel=1e-5)
    model = sum(float(r["model"]) for r in rows) / len(rows)
    assert summary["rollout_rmse"] == pytest.approx(model, rel=1e-5)
    assert summary["improvement_over_baseline"] == pytest.approx(min(means.values()) / model, rel=1e-5)
    with open(reports / "rmse_over_time.csv") as f:
        over_time = list(csv.DictReader(f))
    assert [int(r["step"]) for r in over_time] == list(range(7)) and float(over_time[0]["model"]) == 0
    aware = ["mean_trajectory", "nearest_setting", "linear_settings", "pod_gp"]
    assert set(over_time[0]) == {"step", "model", *baselines, *aware}
    # averaging over steps then trajectories (the summary) = over trajectories then steps (the CSV)
    assert sum(float(r["model"]) for r in over_time[1:]) / 6 == pytest.approx(model, rel=1e-5)
    # the setting-aware baselines, fitted on the 2 training trajectories: the mean one by hand
    train = [Trajectory.load(f) for f in sorted((data_dir / "train").glob("*.pt"))]
    test_traj = Trajectory.load(data_dir / "test" / "traj_200000.pt")
    mean = torch.stack([t.pos.double() for t in train]).mean(0)
    by_hand = float(rollout_rmse(mean, test_traj.pos, test_traj.ply_mask)[1:].mean())
    assert float(rows[0]["mean_trajectory"]) == pytest.approx(by_hand, rel=1e-5)
    assert summary["mean_trajectory_rmse"] == pytest.approx(by_hand, rel=1e-5)
    assert summary["setting_baseline_rmse"] == pytest.approx(min(float(rows[0][k]) for k in aware), rel=1e-6)
    mse = {k: sum(float(r[k]) ** 2 for r in over_time[1:]) / 6 for k in ("model", "mean_trajectory")}
    assert summary["setting_effect_r2"] == pytest.approx(1 - mse["model"] / mse["mean_trajectory"], rel=1e-5)
    assert "best setting-aware baseline" in printed
    for name in ("rmse_over_time.png", "final_shape_traj_200000.png", "xdmf/traj_200000.xdmf"):
        assert (reports / name).is_file(), name

    # predict: new process settings from a file, no ground truth
    settings = tmp_path / "settings.yaml"
    settings.write_text(
        yaml.safe_dump([{"name": "wide", "gripper_positions": [0.2, 0.8], "gripper_forces": [90.0, 10.0]}])
    )
    main(_from_checkpoint("predict", ckpt, data_dir, out, "--data.predict_file", str(settings)))
    predicted = reports / "predict"
    for name in ("wide.xdmf", "wide.png", "wide.json"):
        assert (predicted / name).is_file(), name
    info = json.loads((predicted / "wide.json").read_text())
    assert info["gripper_force"] == [90.0, 10.0]
    # the same settings on a template (a run of the part, as one's own solver data would be)
    mine = tmp_path / "on_template"
    extra = [
        "--data.predict_template",
        str(data_dir / "test" / "traj_200000.pt"),
        "--model.output_dir",
        str(mine),
    ]
    main(_from_checkpoint("predict", ckpt, data_dir, out, "--data.predict_file", str(settings), *extra))
    on_template = json.loads((mine / "predict" / "wide.json").read_text())
    assert on_template["max_e3_displacement_mm"] == pytest.approx(info["max_e3_displacement_mm"], abs=1e-5)

    # settings given with --ckpt_path win where they do not change the network ...
    elsewhere = tmp_path / "elsewhere"
    extra = ["--data.predict_file", str(settings), "--model.output_dir", str(elsewhere)]
    main(_from_checkpoint("predict", ckpt, data_dir, out, *extra, "--model.export_xdmf", "false"))
    assert (elsewhere / "predict" / "wide.png").is_file()
    assert not (elsewhere / "predict" / "wide.xdmf").exists()
    # ... and are refused with a message where they would
    refused = r"model.hidden_channels=8 \(the checkpoint has 16\).*cannot be changed"
    with pytest.raises(SystemExit, match=refused):
        main(_from_checkpoint("test", ckpt, data_dir, out, "--model.hidden_channels", "8"))


def test_change_target_statistics_and_prediction_by_hand(data_dir, monkeypatch):
    """predict_change: statistics of du^t - du^{t-1}; a zero network output keeps the last residual."""
    module, dm = _fitted_module(data_dir, predict_change=True, center_target=False)
    s = module.surrogate
    windows = list(dm.statistics_samples(8))
    change = torch.cat([(w["l0"].target - w["l0"].prev_disp)[w["l0"].ply_mask] for w in windows]).double()
    torch.testing.assert_close(s.target_norm.mean, change.mean(0))
    torch.testing.assert_close(s.target_norm.std, change.std(0, unbiased=False))
    data = windows[-1]
    n = data["l0"].num_nodes
    monkeypatch.setattr(s.diffusion, "sample", lambda *a, **k: torch.zeros(n, 3))
    torch.testing.assert_close(s.predict_residual(data), data["l0"].prev_disp)
    ones = torch.ones(n, 3)
    monkeypatch.setattr(s.diffusion, "sample", lambda *a, **k: ones)
    expected = data["l0"].prev_disp + s.target_norm.std.float()  # scale only, no mean shift
    torch.testing.assert_close(s.predict_residual(data), expected)
    # the loss is the MSE against the normalised change on ply nodes (K = 1: the network output itself)
    captured = {}
    monkeypatch.setattr(s.diffusion, "loss", lambda target, *a, **k: captured.setdefault("t", target).sum())
    s.loss(data)
    ply = data["l0"].ply_mask
    want = ((data["l0"].target - data["l0"].prev_disp) / s.target_norm.std.float())[ply]
    torch.testing.assert_close(captured["t"][ply], want)


def _normalised_error(surrogate, data, seed):
    """``(loss with generator seed, network output - normalised target [N, 3] in float64)``."""
    loss = surrogate.loss(data, generator=torch.Generator().manual_seed(seed))
    x_dict, index_dict, e_dict = surrogate.normalized_features(data)
    target = surrogate.target_norm(data["l0"].target)
    noise = torch.randn(target.shape, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        err = surrogate.model(x_dict, index_dict, e_dict, noise=noise) - target
    return loss, err.double()


def test_huber_loss_of_the_module_by_hand(data_dir):
    """huber_delta: the loss is the Huber form of the squared error on the normalised ply residual."""
    module, dm = _fitted_module(data_dir, huber_delta=0.05)
    s = module.surrogate
    data = list(dm.statistics_samples(8))[-1]
    loss, err = _normalised_error(s, data, 5)
    err = err[data["l0"].ply_mask]
    a = err.abs()
    want = torch.where(a <= 0.05, err * err, 0.1 * a - 0.0025).mean()
    assert (a > 0.05).any() and (a <= 0.05).any()
    torch.testing.assert_close(loss.double(), want, rtol=1e-5, atol=1e-8)
    with pytest.raises(ValueError, match="huber_delta"):
        NextStepLightningModule(**SMALL_MODEL, huber_delta=-1.0)


def test_coarse_loss_of_the_module_by_hand(data_dir):
    """coarse_loss_weight: fine MSE plus the restricted errors of the hierarchy's coarse levels."""
    module, dm = _fitted_module(data_dir, coarse_loss_weight=0.5)
    s = module.surrogate
    data = list(dm.statistics_samples(8))[-1]
    loss, err = _normalised_error(s, data, 5)  # err: [N, 3]
    # dense reference: weighted means over |P| with ply-mask weights, level by level
    w = data["l0"].ply_mask.double()
    want = (err.square() * w[:, None]).sum() / (3 * w.sum())
    e = err
    for k in range(s.num_levels - 1):
        down = data.down(k)
        p = torch.zeros(e.size(0), data[f"l{k + 1}"].num_nodes, dtype=torch.float64)
        p[down.edge_index[0], down.edge_index[1]] = down.edge_weight.double().abs()
        a = p * w[:, None]
        w = a.sum(0)
        assert (w > 0).any() and (w == 0).any()  # tool aggregates hold no ply weight
        e = (a.t() @ e) / w.clamp(min=1e-300)[:, None]
        want = want + 0.5 * (e.square() * w[:, None]).sum() / (3 * w.sum())
    torch.testing.assert_close(loss.double(), want, rtol=1e-5, atol=1e-8)
    plain, _ = _fitted_module(data_dir)
    plain.surrogate.load_state_dict(s.state_dict())
    assert loss > plain.surrogate.loss(data, generator=torch.Generator().manual_seed(5))


class _RecordParameters(L.Callback):
    """Parameters after every optimiser step."""

    def __init__(self):
        self.steps = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps.append({n: p.detach().clone() for n, p in pl_module.named_parameters()})


def _fit_three_steps(data_dir, callbacks):
    L.seed_everything(0)
    module = NextStepLightningModule(**SMALL_MODEL, statistics_samples=8, warmup_steps=1, lr=1e-2)
    dm = AMPNDataModule(str(data_dir), generate=False, max_levels=2, min_coarse_nodes=4, batch_size=2)
    trainer = _quiet_trainer(max_steps=3, callbacks=callbacks)
    trainer.fit(module, datamodule=dm)
    return module


def test_ema_weight_averaging_keeps_statistics_and_averages_by_hand(data_dir):
    from lightning.pytorch.callbacks import EMAWeightAveraging

    record = _RecordParameters()
    plain = _fit_three_steps(data_dir, [record])
    assert len(record.steps) == 3
    averaged = _fit_three_steps(data_dir, [EMAWeightAveraging(decay=0.5)])
    # EMA by hand: the first update copies, then a <- 0.5 a + 0.5 theta
    for name, p in averaged.named_parameters():
        a = record.steps[0][name]
        for theta in record.steps[1:]:
            a = 0.5 * a + 0.5 * theta[name]
        torch.testing.assert_close(p.detach(), a, rtol=1e-6, atol=1e-7)
    # the normalisation statistics (buffers) survive the averaging exactly
    for (name, b_plain), (_, b_avg) in zip(plain.named_buffers(), averaged.named_buffers(), strict=True):
        assert torch.equal(b_plain, b_avg), name
    assert averaged.surrogate.statistics_frozen


def _fit_three_steps_compiled(data_dir, **kwargs):
    """3 steps of a flat network of one layer: the compile of the training step (forward and
    backward, dynamic shapes) is what the compile tests here are about; the compiled V-cycle's
    layers are checked against eager in tests/test_nn_compile.py, at a fraction of this compile time."""
    L.seed_everything(0)
    model = {**SMALL_MODEL, "num_levels": 1, "pre_layers": 0, "post_layers": 0}
    module = NextStepLightningModule(**model, statistics_samples=8, warmup_steps=1, lr=1e-2, **kwargs)
    dm = AMPNDataModule(str(data_dir), generate=False, max_levels=1, min_coarse_nodes=4, batch_size=2)
    _quiet_trainer(max_steps=3).fit(module, datamodule=dm)
    return module


@pytest.mark.slow
def test_compiled_training_matches_eager_and_keeps_checkpoint_keys(data_dir, monkeypatch):
    """``compile_network`` through the Trainer: Dynamo's capture and AOT autograd's forward and
    backward graphs (backend ``aot_eager``); Inductor's forward and backward kernels are checked
    on one layer in tests/test_nn_compile.py, at a fraction of the whole network's compile."""
    import functools

    torch._dynamo.reset()
    eager = _fit_three_steps_compiled(data_dir)
    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="aot_eager"))
    compiled = _fit_three_steps_compiled(data_dir, compile_network=True)
    torch._dynamo.reset()
    assert compiled._compiled_network not in (None, False)  # the compiled network trained
    assert list(compiled.state_dict()) == list(eager.state_dict())  # no _orig_mod keys
    for (name, p_eager), (_, p_comp) in zip(
        eager.named_parameters(), compiled.named_parameters(), strict=True
    ):
        torch.testing.assert_close(p_comp, p_eager, rtol=1e-4, atol=1e-5, msg=name)


def test_compile_failure_falls_back_to_eager_with_a_warning(data_dir, monkeypatch):
    import torch_ampn.training.module as module_mod

    def broken_compile(model, **kwargs):
        def run(*args, **kw):
            raise RuntimeError("no C++ compiler")

        return run

    monkeypatch.setattr(module_mod.torch, "compile", broken_compile)
    eager = _fit_three_steps_compiled(data_dir)
    with pytest.warns(UserWarning, match="torch.compile failed.*no C\\+\\+ compiler"):
        fallback = _fit_three_steps_compiled(data_dir, compile_network=True)
    assert fallback._compiled_network is False
    for (name, p_eager), (_, p_fb) in zip(eager.named_parameters(), fallback.named_parameters(), strict=True):
        torch.testing.assert_close(p_fb, p_eager, rtol=0, atol=0, msg=name)


# ---- module arguments and old checkpoints ------------------------------------------------------
def test_surrogate_arguments_of_the_module_match_the_surrogate_and_the_network():
    import inspect

    from torch_ampn.forming import AMPNSurrogate
    from torch_ampn.nn import RobinAMPN
    from torch_ampn.training.checkpoint import module_defaults
    from torch_ampn.training.next_step_module import SURROGATE_ARGUMENTS

    module = module_defaults(NextStepLightningModule)
    # the forming network is RobinAMPN (the paper's settings), not the generic AMPN's defaults
    owners = {**inspect.signature(RobinAMPN).parameters, **inspect.signature(AMPNSurrogate).parameters}
    for name in SURROGATE_ARGUMENTS:
        assert name in module and name in owners, name
        assert module[name] == owners[name].default, name
    # every surrogate argument of the module reaches the network
    model = NextStepLightningModule(**{**SMALL_MODEL, "mlp_channels": 24, "aggr": "mean"}).surrogate.model
    assert (model.hidden_channels, model.mlp_channels, model.aggr, model.num_levels) == (16, 24, "mean", 2)
    assert [len(s) for s in (model.pre, model.down, model.solve, model.post, model.up)] == [1] * 5


def test_checkpoint_of_version_0_1_0_dev0_loads_and_predicts_as_it_did(tmp_path, small_sim):
    """A checkpoint written before ``mlp_channels`` existed (MLPs as wide as d = 8), with the
    residual that version predicted for a fixed window (made by ``tests/data`` 's writer)."""
    from pathlib import Path

    from torch_ampn.data import HierarchyCache

    data = Path(__file__).parent / "data"
    ref = torch.load(data / "legacy_0.1.0.dev0_reference.pt", weights_only=True)
    legacy = data / "legacy_0.1.0.dev0.ckpt"
    assert "mlp_channels" not in torch.load(legacy, weights_only=True)["hyper_parameters"]
    module = NextStepLightningModule.load_from_checkpoint(legacy, weights_only=True)
    assert module.hparams.mlp_channels == module.hparams.hidden_channels == 8
    assert module.surrogate.model.pre[0].mlp_contact.hidden_channels == 8
    # the reference's run is seed 3 of the small setting with the material of its day (data version 1)
    assert StampFormingConfig(**ref["config"]) == small_sim and ref["seed"] == 3
    traj = simulate_batch(StampFormingConfig(**ref["config"], **MATERIAL_V1, **PHYSICS_V2), [3])[0]
    cache = HierarchyCache(None, max_levels=ref["max_levels"], min_coarse_nodes=ref["min_coarse_nodes"])
    window = module.surrogate.contact(step_sample(traj, ref["t"], cache(traj)))
    generator = torch.Generator().manual_seed(ref["generator_seed"])
    with torch.no_grad():
        residual = module.surrogate.predict_residual(window, generator)
    torch.testing.assert_close(residual, ref["residual"], rtol=1e-5, atol=1e-6)
    # saved again, the checkpoint records the width and loads without the legacy path
    path = tmp_path / "again.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": L.__version__}, path)  # fmt: skip
    again = NextStepLightningModule.load_from_checkpoint(path, weights_only=True)
    assert again.hparams.mlp_channels == 8
    for name, value in module.state_dict().items():
        assert torch.equal(value, again.state_dict()[name]), name


def _assert_same_state(state, reference):
    """Equal state dicts: tensors bit for bit, extra states (dicts) by value."""
    assert state.keys() == reference.keys()
    for name, value in reference.items():
        same = torch.equal(state[name], value) if isinstance(value, torch.Tensor) else state[name] == value
        assert same, name


def _pre_split_checkpoint(module, path, mode):
    """``module`` saved as the one module of both models saved it before 2026-12-07: every argument
    of both models (the other's unused) and ``mode``, no ``torch_ampn_model`` field."""
    from torch_ampn.training import DirectLightningModule
    from torch_ampn.training.checkpoint import module_defaults

    both = {**module_defaults(NextStepLightningModule), **module_defaults(DirectLightningModule)}
    hparams = {**both, **dict(module.hparams), "mode": mode, "rollout_seed": 7}  # a next-step knob, unused
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams,
                "pytorch-lightning_version": L.__version__}, path)  # fmt: skip
    return path


def test_a_direct_checkpoint_from_before_the_split_loads_as_a_direct_module(tmp_path, data_dir):
    from torch_ampn.training import DirectLightningModule, load_module

    torch.manual_seed(0)
    module = DirectLightningModule(
        **{k: v for k, v in SMALL_MODEL.items() if k != "fast_rollout"}, base="initial"
    )
    dm = _datamodule(data_dir, mode="direct")
    module.fit_statistics(dm.statistics_samples(2))
    path = _pre_split_checkpoint(module, tmp_path / "old_direct.ckpt", "direct")
    for loaded in (load_module(path), DirectLightningModule.load_from_checkpoint(path)):
        assert type(loaded) is DirectLightningModule and loaded.hparams.base == "initial"
        assert "mode" not in loaded.hparams and "rollout_seed" not in loaded.hparams
        _assert_same_state(loaded.state_dict(), module.state_dict())
    with pytest.raises(
        SystemExit, match=r"model.pushforward=0.5 \(not an argument of the checkpoint's model\)"
    ):
        main(["test", "--ckpt_path", str(path), "--model.pushforward", "0.5"])
    with pytest.raises(
        ValueError, match=r"old_direct.ckpt: holds a direct model, not a NextStepLightningModule's"
    ):
        NextStepLightningModule.load_from_checkpoint(path)


def test_the_committed_next_step_checkpoint_from_before_the_split_loads_both_ways():
    from torch_ampn.training import DirectLightningModule, load_module

    saved = torch.load(TINY_CKPT, weights_only=True)
    assert (
        saved["hyper_parameters"].get("mode", "next_step") == "next_step" and "torch_ampn_model" not in saved
    )
    a, b = load_module(TINY_CKPT), NextStepLightningModule.load_from_checkpoint(TINY_CKPT)
    assert type(a) is type(b) is NextStepLightningModule
    assert a.hparams.hidden_channels == saved["hyper_parameters"]["hidden_channels"]
    _assert_same_state(a.state_dict(), saved["state_dict"])
    _assert_same_state(b.state_dict(), saved["state_dict"])
    with pytest.raises(ValueError, match="holds a next_step model, not a DirectLightningModule's"):
        DirectLightningModule.load_from_checkpoint(TINY_CKPT)


def test_a_new_checkpoint_names_its_model_and_the_cli_refuses_the_other_models_config():
    configs = Path(__file__).resolve().parents[1] / "examples" / "configs"
    module = NextStepLightningModule(**SMALL_MODEL)
    checkpoint = {}
    module.on_save_checkpoint(checkpoint)
    assert checkpoint["torch_ampn_model"] == "next_step"
    with pytest.raises(
        SystemExit, match=r"tiny.ckpt: holds a NextStepLightningModule, not the DirectLightningModule"
    ):
        main(["test", "--config", str(configs / "direct.yaml"), "--ckpt_path", str(TINY_CKPT)])
    with pytest.raises(SystemExit, match=r"holds a NextStepLightningModule, not the DirectLightningModule"):
        main(["test", "--ckpt_path", str(TINY_CKPT), "--model", "DirectLightningModule"])


def test_a_config_or_flag_with_the_old_model_mode_is_refused_in_one_line(tmp_path):
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump({"model": {"mode": "direct", "hidden_channels": 8}}))
    with pytest.raises(SystemExit, match=rf"^torch-ampn: {old}: model.mode is gone: name the module instead"):
        main(["fit", "--config", str(old)])
    with pytest.raises(SystemExit, match=r"^torch-ampn: --model.mode: model.mode is gone"):
        main(["fit", "--model.mode", "direct"])


# ---- bad input: one line naming the file and the field ------------------------------------------
@pytest.mark.parametrize(
    "name, text, message",
    [
        ("broken.json", '[{"gripper_positions": [0.5, 0.5], ', r"broken.json: not valid JSON \(Expecting"),
        ("broken.yaml", "- gripper_positions: [0.5, 0.5\n  gripper_forces: 3",
         r"broken.yaml: not valid YAML \("),
        ("object.json", '{"gripper_positions": [0.5]}', r"object.json: expected a non-empty list"),
        ("words.yaml", "- {gripper_positions: [a, b], gripper_forces: [1, 2]}",
         r"words.yaml: setting 0, field 'gripper_positions': expected a list of numbers"),
        ("three.json", '[{"name": "t", "gripper_positions": [0.1, 0.2, 0.3], "gripper_forces": [1, 2]}]',
         r"three.json: setting 0 \(t\): gripper_positions needs 2 values, got 3"),
        ("outside.json", '[{"gripper_positions": [0.5, 1.5], "gripper_forces": [1, 2]}]',
         r"outside.json: setting 0 \(setting_000\): gripper_positions are fractions of the edge in \[0, 1\]"),
    ],
)  # fmt: skip
def test_bad_predict_files_are_refused_naming_file_and_field(data_dir, tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    dm = AMPNDataModule(str(data_dir), generate=False, predict_file=str(path), min_coarse_nodes=4)
    with pytest.raises(ValueError, match=message) as info:
        dm.setup("predict")
    assert "\n" not in str(info.value)


def test_bad_checkpoints_and_input_errors_end_in_one_line(data_dir, tmp_path):

    truncated = tmp_path / "truncated.ckpt"
    legacy = Path(__file__).parent / "data" / "legacy_0.1.0.dev0.ckpt"
    truncated.write_bytes(legacy.read_bytes()[:5000])
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"lr": 1.0}}, foreign)
    cases = [
        (truncated, r"truncated.ckpt: not a readable checkpoint \("),
        (foreign, r"foreign.ckpt: not a torch-ampn checkpoint \(field 'hyper_parameters'"),
        (tmp_path / "missing.ckpt", r"missing.ckpt: no such checkpoint file"),
    ]
    for path, message in cases:
        with pytest.raises(SystemExit, match=message):
            main(["test", "--ckpt_path", str(path), "--data.data_dir", str(data_dir)])
    # the console script: an input error is one line on stderr, exit status 1, no traceback
    bad = tmp_path / "broken.json"
    bad.write_text("[")
    args = ["predict", "--ckpt_path", str(legacy), "--data.data_dir", str(data_dir)]
    args += ["--data.generate", "false", "--data.min_coarse_nodes", "4", "--data.predict_file", str(bad)]
    args += ["--trainer.logger", "false"]
    script = "from torch_ampn.cli.train import entry_point; entry_point()"
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, cwd=tmp_path)
    last = done.stderr.strip().splitlines()[-1]
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert last.startswith("torch-ampn: error: ") and f"{bad}: not valid JSON" in last


def test_an_output_folder_that_cannot_be_written_stops_fit_before_training(data_dir, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("a file where the folder should be")
    module = NextStepLightningModule(**SMALL_MODEL, output_dir=str(blocked / "reports"))
    trainer = _quiet_trainer(max_steps=2)
    message = f"{blocked / 'reports'}: cannot write there \\(model.output_dir\\)"
    with pytest.raises(PermissionError, match=message):
        trainer.fit(module, datamodule=_datamodule(data_dir))
    assert trainer.global_step == 0 and not module.surrogate.statistics_frozen  # before any work


@pytest.mark.xdist_group("tiny_fit")
def test_a_fit_killed_with_sigkill_resumes_bit_for_bit(tiny_fit, tmp_path):
    """``kill -9`` during ``fit``, then ``--ckpt_path last.ckpt``: the same weights as an uninterrupted fit.

    Bit for bit on the CPU: the checkpoint holds the random generators' states and the
    training loader's position (its epoch order depends on the seed and the epoch only), so
    the resumed run trains on the same batches with the same noise from the step it stopped at.
    """
    data_dir, whole = tiny_fit  # the uninterrupted fit
    config, out = fit_config(tmp_path / "killed", data_dir)
    last = out / "ckpt" / "last.ckpt"
    killing = yaml.safe_load(config.read_text())
    killing["trainer"]["callbacks"].append(
        {
            "class_path": "helpers.SigkillAtStep",
            "init_args": {"step": 3, "expect": str(last)},  # last.ckpt of the validation at step 3
        }
    )
    killing_path = tmp_path / "killed" / "killing.yaml"
    killing_path.write_text(yaml.safe_dump(killing))
    # the same thread count as this process's fits: the summation order of a reduction depends on it
    threads = torch.get_num_threads()
    script = f"import sys, torch; torch.set_num_threads({threads}); "
    script += "from torch_ampn.cli.train import main; main(sys.argv[1:])"
    done = subprocess.run(
        [sys.executable, "-c", script, "fit", "--config", str(killing_path)],
        capture_output=True, text=True, cwd=tmp_path, env={**os.environ, "PYTHONPATH": helpers.PYTHONPATH},
    )  # fmt: skip
    assert done.returncode == -signal.SIGKILL, done.stderr[-2000:]
    assert torch.load(last, weights_only=True)["global_step"] == 3
    assert not (out / "ckpt" / "epoch=0-step=6.ckpt").exists()  # it did not get further

    main(["fit", "--config", str(config), "--ckpt_path", str(last)])
    a = torch.load(whole / "ckpt" / "last.ckpt", weights_only=True)
    b = torch.load(last, weights_only=True)
    assert a["global_step"] == b["global_step"] == 6
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for name, value in a["state_dict"].items():
        assert torch.equal(value, b["state_dict"][name]), name
    states_a, states_b = a["optimizer_states"][0]["state"], b["optimizer_states"][0]["state"]
    assert states_a.keys() == states_b.keys()
    for i in states_a:
        assert all(torch.equal(states_a[i][key], states_b[i][key]) for key in states_a[i])


def test_the_data_module_interface_is_declared_and_a_fit_without_it_is_refused(data_dir):
    """AMPNDataModule is a ForecastDataSource; a plain LightningDataModule is not, and a fit from
    scratch on it stops in one line before any step (the statistics need the interface)."""
    from torch.utils.data import DataLoader

    from torch_ampn.training import ForecastDataSource

    assert isinstance(_datamodule(data_dir), ForecastDataSource)
    windows = list(_datamodule(data_dir).statistics_samples(4))

    class Plain(L.LightningDataModule):
        def train_dataloader(self):
            return DataLoader(windows, batch_size=None)

    assert not isinstance(Plain(), ForecastDataSource)
    module = NextStepLightningModule(**SMALL_MODEL)
    with pytest.raises(RuntimeError, match="ForecastDataSource's methods"):
        _quiet_trainer(2).fit(module, datamodule=Plain())
    assert module.trainer.global_step == 0
