"""Temporal bundling: one call of a next-step model predicts the next B saved steps."""

import math

import pytest
import torch
import yaml

pytest.importorskip("lightning")

from make_fixtures import SMALL_MODEL, fit_config  # noqa: E402

from torch_ampn.cli.train import main  # noqa: E402
from torch_ampn.data import HierarchyCache, step_sample  # noqa: E402
from torch_ampn.forming import AMPNSurrogate, load_surrogate  # noqa: E402
from torch_ampn.rollout import one_step_predictions, rollout, rollout_plain, rollout_rmse  # noqa: E402
from torch_ampn.rollout.fast import fast_path_supported  # noqa: E402
from torch_ampn.training import AMPNDataModule, NextStepLightningModule, load_module  # noqa: E402

SIZES = dict(hidden_channels=8, mlp_channels=8, pre_layers=1, down_layers=1, solve_layers=1, post_layers=1,
             up_layers=1)  # fmt: skip


@pytest.fixture(scope="module")
def hierarchy(small_runs):
    return HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(small_runs[0])


def test_a_bundled_window_holds_the_offsets_of_the_next_steps(small_runs, hierarchy):
    """Block k - 1 is x^{t-1+k} - x^{t-1}, steps past the last repeat it; tools' bc_disp is the same."""
    traj = small_runs[0]
    last = traj.num_steps  # 6
    t, bundle = 5, 4  # steps 5, 6, then 7 and 8 past the end (= step 6)
    window = step_sample(traj, t, hierarchy, bundle)
    fine = window["l0"]
    assert fine.target.shape == (traj.num_nodes, 3 * bundle)
    for k, s in enumerate([5, 6, last, last]):
        expected = traj.pos[s] - traj.pos[t - 1]
        torch.testing.assert_close(fine.target[:, 3 * k : 3 * k + 3], expected, atol=0, rtol=0)
    ply = traj.ply_mask
    assert torch.equal(fine.bc_disp[ply], torch.zeros_like(fine.bc_disp[ply]))
    assert torch.equal(fine.bc_disp[~ply], fine.target[~ply])
    one = step_sample(traj, t, hierarchy)  # B = 1: the plain next-step window
    assert torch.equal(one["l0"].target, traj.pos[t] - traj.pos[t - 1])
    assert torch.equal(one["l0"].pos, fine.pos) and torch.equal(one["l0"].prev_disp, fine.prev_disp)


@pytest.mark.parametrize("bundle", [1, 2, 4])
def test_a_bundled_rollout_compounds_a_constant_error_once_per_call(small_runs, hierarchy, bundle):
    """A predictor off by b on every offset (hand computation): teacher forced, every step errs |b|;
    rolled out, step t errs ceil(t / B) |b| (one b per call so far), not t |b| as with B = 1."""
    traj = small_runs[0]
    bias = torch.tensor([0.3, -0.4, 1.2])  # |b| = 1.3 mm; its RMSE over 3 coordinates is |b| / sqrt 3
    calls = []

    def biased(data):
        t = int(data.step)
        calls.append(t)
        ahead = [min(t - 1 + k, traj.num_steps) for k in range(1, bundle + 1)]
        true = torch.cat([traj.pos[s] - traj.pos[t - 1] for s in ahead], dim=-1)  # [N, 3 B]
        return true + bias.repeat(bundle)

    ply = traj.ply_mask
    per_call = 1.3 / math.sqrt(3)
    full = rollout_plain(biased, traj, hierarchy, bundle_steps=bundle)
    assert calls == list(range(1, traj.num_steps + 1, bundle))  # ceil(6 / B) calls
    steps = torch.arange(traj.num_steps + 1)
    expected = torch.ceil(steps / bundle).double() * per_call
    torch.testing.assert_close(rollout_rmse(full, traj.pos, ply).double(), expected, atol=1e-3, rtol=0)
    assert torch.equal(full[:, ~ply], traj.pos[:, ~ply].float())  # tools on their path
    one = rollout_rmse(one_step_predictions(biased, traj, hierarchy, bundle_steps=bundle), traj.pos, ply)
    torch.testing.assert_close(one[1:].double(), torch.full((traj.num_steps,), per_call).double(), atol=1e-4,
                               rtol=0)  # fmt: skip
    with pytest.raises(ValueError, match="returned 3 columns per node; bundle_steps=2 needs 6"):
        rollout_plain(lambda d: torch.zeros_like(d["l0"].pos), traj, hierarchy, bundle_steps=2)


def test_a_bundled_surrogate_predicts_b_steps_per_call_and_survives_a_model_file(
    small_runs, hierarchy, tmp_path
):
    traj = small_runs[0]
    surrogate = AMPNSurrogate(num_levels=2, bundle_steps=3, contact_radius=12.0, contact_k=1, **SIZES)
    for t in range(1, traj.num_steps + 1):
        surrogate.accumulate_statistics(surrogate.contact(step_sample(traj, t, hierarchy, 3)))
    surrogate.freeze_statistics()
    window = surrogate.contact(step_sample(traj, 2, hierarchy, 3))
    out = surrogate.predict_residual(window, torch.Generator().manual_seed(0))
    assert out.shape == (traj.num_nodes, 9)
    assert "bundle_steps" in fast_path_supported(surrogate)
    with pytest.warns(RuntimeWarning, match="no fast rollout .*bundle_steps=3"):
        pred = rollout(surrogate, traj, hierarchy, surrogate.contact, fast=True,
                       generator=torch.Generator().manual_seed(0))  # fmt: skip
    generator = torch.Generator().manual_seed(0)
    plain = rollout(lambda d: surrogate.predict_residual(d, generator), traj, hierarchy, surrogate.contact,
                    bundle_steps=3)  # fmt: skip
    assert pred.shape == traj.pos.shape and torch.isfinite(pred).all()
    assert torch.equal(pred[:, ~traj.ply_mask], traj.pos[:, ~traj.ply_mask])
    assert torch.equal(pred, plain)  # the fallback is the plain path of 3 steps per call
    path = surrogate.save(tmp_path / "bundled.pt")
    loaded = load_surrogate(path)
    assert loaded.bundle_steps == 3
    again = loaded.predict_residual(window, torch.Generator().manual_seed(0))
    torch.testing.assert_close(again, out)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (dict(bundle_steps=0), "bundle_steps must be an integer >= 1, got 0"),
        (dict(bundle_steps=2, predict_change=True), "bundle_steps > 1 does not work with predict_change"),
        (dict(bundle_steps=2, prior_features=True), "bundle_steps > 1 does not work with prior_features"),
    ],
)
def test_bundle_settings_a_surrogate_cannot_have_are_refused_in_one_line(options, message):
    with pytest.raises(ValueError, match=message):
        AMPNSurrogate(num_levels=2, **SIZES, **options)


def test_a_bundled_module_refuses_pushforward_and_data_of_another_bundle(tiny_data):
    with pytest.raises(ValueError, match="pushforward > 0 does not work with bundle_steps > 1"):
        NextStepLightningModule(bundle_steps=2, pushforward=0.5, **SMALL_MODEL)
    module = NextStepLightningModule(bundle_steps=2, **SMALL_MODEL)
    data = AMPNDataModule(data_dir=str(tiny_data), generate=False, min_coarse_nodes=4)
    with pytest.raises(ValueError, match="model.bundle_steps=2 but data.bundle_steps=1"):
        data.check_model(module.surrogate)


@pytest.mark.slow
def test_cli_fits_and_tests_a_bundled_model(tmp_path, tiny_data):
    """``--model.bundle_steps 3`` reaches the data module (linked): the fit learns 3-step windows."""
    config, out = fit_config(tmp_path, tiny_data)
    settings = yaml.safe_load(config.read_text())
    settings["model"]["bundle_steps"] = 3
    config.write_text(yaml.safe_dump(settings))
    main(["fit", "--config", str(config)])
    module = load_module(out / "ckpt" / "last.ckpt")
    assert module.surrogate.bundle_steps == 3
    assert module.surrogate.target_norm.mean.shape == (9,)  # statistics of the 3 bundled offsets
    main(["test", "--config", str(config), "--ckpt_path", str(out / "ckpt" / "last.ckpt")])
    report = next((out / "reports").rglob("test_rmse.csv"))
    assert report.exists()
