"""The setting-aware baselines against hand cases and exact interpolation, and the spread measurement."""

import dataclasses
import json

import pytest
import torch

from torch_ampn.baselines import (
    MeanTrajectory,
    NearestSetting,
    PODRegression,
    fit_setting_baselines,
    process_settings,
    rollout_mse,
    setting_effect_r2,
)
from torch_ampn.data.node_type import NodeType
from torch_ampn.testing import small_trajectory

TEMPLATE = small_trajectory(steps=3)
PLY = TEMPLATE.node_type == NodeType.PLY


def _with_settings(position: float, force: float, shift) -> "torch_ampn.data.Trajectory":  # noqa: F821
    """The template with one gripper at ``position`` pulling ``force`` N, its plies moved by
    ``shift(step)`` ``[N, 3]`` at every step (the tools stay put)."""
    pos = TEMPLATE.pos.clone()
    for t in range(pos.size(0)):
        pos[t, PLY] = TEMPLATE.pos[0, PLY] + shift(t)[PLY]
    return dataclasses.replace(
        TEMPLATE,
        pos=pos,
        gripper_force=torch.tensor([force]),
        meta={"gripper_edge_fraction": [position], "name": f"at {position} with {force} N"},
    )


def _uniform(value: float):
    """A shift of every ply node by ``value * t`` mm along e3 at step ``t``."""
    return lambda t: torch.tensor([0.0, 0.0, value * t]).expand(TEMPLATE.num_nodes, 3)


def _smooth(position: float, force: float):
    """A shift that varies smoothly (and nonlinearly) with the settings and over the nodes."""
    x0 = TEMPLATE.pos[0]

    def shift(t):
        wave = torch.sin(x0[:, :1] + 3 * position) * (force / 50.0) ** 2  # [N, 1]
        return t * torch.cat([wave, 0.5 * wave, torch.cos(x0[:, 1:2] * position) * force / 100], 1)

    return shift


# ---- hand cases ---------------------------------------------------------------------------
A = _with_settings(0.2, 10.0, _uniform(1.0))
B = _with_settings(0.8, 90.0, _uniform(3.0))


def test_settings_are_the_edge_fractions_then_the_forces():
    assert process_settings(A).tolist() == [0.2, 10.0]
    with pytest.raises(ValueError, match="meta has no 'gripper_edge_fraction'"):
        process_settings(TEMPLATE)


def test_the_mean_of_two_trajectories_is_their_midway():
    query = _with_settings(0.5, 50.0, _uniform(0.0))
    pred = MeanTrajectory().fit([A, B]).predict(query)
    expected = _with_settings(0.5, 50.0, _uniform(2.0)).pos  # shifts 1 and 3 per step: 2
    torch.testing.assert_close(pred, expected)
    assert torch.equal(pred[:, ~PLY], query.pos[:, ~PLY])  # the tools are the query's own


def test_the_nearest_setting_is_found_in_standardised_settings():
    nearest = NearestSetting().fit([A, B])
    # standardised (mean 0.5 and 50 N, std 0.3 and 40 N): (0.75, 45 N) is (0.83, -0.125), squared
    # distances 4.13 from A at (-1, -1) and 1.29 from B at (1, 1); in raw units A is nearer (35 N)
    for settings, expected in [((0.3, 20.0), A), ((0.75, 80.0), B), ((0.75, 45.0), B), ((0.4, 35.0), A)]:
        query = _with_settings(*settings, _uniform(0.0))
        torch.testing.assert_close(nearest.predict(query), expected.pos)
    assert nearest.nearest(torch.tensor([[0.75, 45.0], [0.4, 35.0]]).numpy()).tolist() == [1, 0]


def test_a_linear_regression_is_exact_on_a_linear_setting_effect():
    """Plies shifted by (position + force / 100) mm per step: an affine map of the settings."""
    train = [
        _with_settings(p, f, _uniform(p + f / 100)) for p, f in [(0.2, 10), (0.8, 90), (0.5, 20), (0.3, 70)]
    ]
    model = PODRegression("linear", num_components=None).fit(train)
    query = _with_settings(0.6, 40.0, _uniform(0.0))
    torch.testing.assert_close(
        model.predict(query), _with_settings(0.6, 40.0, _uniform(1.0)).pos, atol=1e-4, rtol=0
    )


SETTINGS = [(0.15, 5.0), (0.3, 80.0), (0.45, 30.0), (0.6, 95.0), (0.75, 15.0), (0.85, 60.0), (0.5, 55.0)]
SMOOTH = [_with_settings(p, f, _smooth(p, f)) for p, f in SETTINGS]


@pytest.mark.parametrize("regressor", ["gp", "rbf"])
def test_pod_regression_reproduces_its_training_trajectories(regressor):
    model = PODRegression(regressor, num_components=None, noise=False).fit(SMOOTH)
    assert len(model.explained_variance_ratio) <= len(SMOOTH) - 1
    for traj in SMOOTH:
        torch.testing.assert_close(model.predict(traj), traj.pos, atol=1e-4, rtol=0)
    together = model.predict_many(SMOOTH[::-1])  # one batch of settings: each as predicted alone
    for traj, pred in zip(SMOOTH[::-1], together, strict=True):
        torch.testing.assert_close(pred, model.predict(traj), atol=1e-6, rtol=0)
    assert model.predict_many([]) == []


def test_pod_gp_beats_the_mean_and_the_nearest_setting_between_training_settings():
    test = [_with_settings(p, f, _smooth(p, f)) for p, f in [(0.35, 50.0), (0.7, 40.0), (0.55, 75.0)]]
    models = {
        "mean": MeanTrajectory(),
        "nearest": NearestSetting(),
        "gp": PODRegression("gp", num_components=None, noise=False),
    }
    mse = {
        name: sum(rollout_mse(m.fit(SMOOTH).predict(t), t.pos, PLY) for t in test) / 3
        for name, m in models.items()
    }
    assert mse["gp"] < mse["nearest"] and mse["gp"] < mse["mean"]
    assert setting_effect_r2(mse["gp"], mse["mean"]) > 0.5
    assert setting_effect_r2(mse["mean"], mse["mean"]) == 0.0


def test_a_baseline_fitted_before_is_reused_and_the_others_are_fitted():
    """The data module's prior (fitted once) is not fitted again for the test report."""
    prior = PODRegression("gp").fit(SMOOTH)
    fitted, reason = fit_setting_baselines(SMOOTH, {"pod_gp": prior})
    assert reason is None and fitted["pod_gp"] is prior
    assert list(fitted) == ["mean_trajectory", "nearest_setting", "linear_settings", "pod_gp"]
    torch.testing.assert_close(
        fitted["mean_trajectory"].predict(SMOOTH[0]), MeanTrajectory().fit(SMOOTH).predict(SMOOTH[0])
    )


def test_a_fraction_of_the_variance_keeps_the_leading_components():
    model = PODRegression("linear", num_components=0.9).fit(SMOOTH)
    ratios = model.explained_variance_ratio
    assert ratios.sum() >= 0.9 and (len(ratios) == 1 or ratios[:-1].sum() < 0.9)


def test_another_mesh_is_refused_in_one_line():
    other = dataclasses.replace(A, pos=A.pos[:, :-1], component=A.component[:-1], node_type=A.node_type[:-1])
    with pytest.raises(ValueError, match=r"field 'pos' differs .* one mesh"):
        MeanTrajectory().fit([A, other])
    moved = dataclasses.replace(B, pos=B.pos + 5.0)
    with pytest.raises(ValueError, match="field 'pos' starts elsewhere"):
        NearestSetting().fit([A]).predict(moved)
    with pytest.raises(ValueError, match="regressor must be"):
        PODRegression("kriging")
    with pytest.raises(ValueError, match=r"settings need 2 columns"):
        MeanTrajectory().fit([A, B]).predict_settings([[0.1, 2.0, 3.0]])


# ---- the spread and the chaos floor ---------------------------------------------------------
def test_the_spread_of_two_trajectories_by_hand():
    from torch_ampn.sim.spread import setting_spread

    # plies 1 and 3 mm/step along e3: each 1 mm/step from the mean, 2 mm/step apart. Steps 1..3
    # hold t mm and 2t mm: the per-step RMSE (over 3 coordinates) is t / sqrt(3), resp. 2t / sqrt(3)
    spread = setting_spread([A, B])
    assert spread["from_mean"]["mean"] == pytest.approx(2 / 3**0.5, rel=1e-6)
    assert spread["pairs"]["mean"] == pytest.approx(4 / 3**0.5, rel=1e-6) and spread["pairs"]["count"] == 1
    # B's plies move 3 mm per step, 9 mm in the 3 steps
    assert spread["max_step_mm"] == pytest.approx(3.0) and spread["max_displacement_mm"] == pytest.approx(9.0)
    assert spread["tool_travel_mm"] == 0.0  # the template's die stays put


def test_spread_report_flags_a_blow_up_by_total_and_by_step_motion():
    """Aims met only without a blow-up: a node past 1.25x the tools' travel, or half of it in a step."""
    from torch_ampn.sim.spread import spread_report

    def report(max_step: float, max_disp: float) -> dict:
        spread = {
            "trajectories": 2,
            "from_mean": {"mean": 2.0},
            "pairs": {"mean": 3.0},
            "max_step_mm": max_step,
            "max_displacement_mm": max_disp,
            "tool_travel_mm": 60.0,
        }
        return spread_report(spread, {"mean": 0.2})

    healthy = report(23.0, 53.0)  # the largest motions of healthy coarse runs (2026-12-02)
    assert (
        not healthy["blown_up"]
        and healthy["meets_aims"]
        and healthy["spread_over_floor"] == pytest.approx(10)
    )
    assert report(23.0, 79.0)["blown_up"] and not report(23.0, 79.0)["meets_aims"]  # 79 > 1.25 * 60
    assert report(37.0, 53.0)["blown_up"]  # 37 > 0.5 * 60 within one step
    assert not report(29.9, 74.9)["blown_up"]


@pytest.mark.slow
def test_the_chaos_floor_and_the_spread_command(quick_sim, tmp_path, capsys):
    """The same settings from a start moved by 1e-6 mm: a small but real difference; the command's JSON."""
    from torch_ampn.cli.data import main
    from torch_ampn.sim import simulate_batch
    from torch_ampn.sim.config import StampFormingConfig
    from torch_ampn.sim.spread import chaos_floor, trajectory_rmse

    runs = simulate_batch(quick_sim, seeds=[3, 4])
    traj = runs[0]
    cfg = StampFormingConfig.from_dict(traj.meta["config"])
    again = simulate_batch(cfg, [traj.meta["seed"]], perturbation=0.0)[0]
    assert torch.equal(again.pos, traj.pos)  # eager: the same settings repeat bit for bit
    floor = chaos_floor([traj], perturbation=1e-6)
    # a small but real difference: under a tenth of what the other setting changes (the aim)
    assert 0 < floor["mean"] < 0.1 * trajectory_rmse(runs[1], traj) and floor["count"] == 1
    moved = simulate_batch(cfg, [traj.meta["seed"]], perturbation=1e-6)[0]
    start = (moved.pos[0] - traj.pos[0]).abs()
    assert moved.meta["initial_perturbation"] == 1e-6 and 0 < float(start.max()) <= 1e-5  # float32 rounding
    # the command on a folder of the two runs
    (tmp_path / "train").mkdir()
    for i, t in enumerate(runs):
        t.save(tmp_path / "train" / f"traj_{i:06d}.pt")
    assert main(["spread", str(tmp_path), "--chaos", "1", "--json", str(tmp_path / "spread.json")]) == 0
    report = json.loads((tmp_path / "spread.json").read_text())
    assert report["chaos_floor"]["mean"] == pytest.approx(floor["mean"])
    assert report["spread_over_floor"] == pytest.approx(report["from_mean"]["mean"] / floor["mean"])
    assert report["tool_travel_mm"] == pytest.approx(quick_sim.stroke, abs=1e-3) and not report["blown_up"]
    assert "spread / floor" in capsys.readouterr().out


def test_two_run_reliability_by_hand(small_runs):
    """Two identical runs agree perfectly; a second run that reverses the settings' order ranks
    them backwards; ``within`` is the hand formula sqrt(mean((a - b)^2) / 2)."""
    import math

    from torch_ampn.design.measures import part_quality
    from torch_ampn.sim.spread import two_run_reliability

    a, b = small_runs
    mid = dataclasses.replace(a, pos=0.5 * (a.pos + b.pos))  # a third part between the two
    runs = [a, mid, b]
    same = two_run_reliability(runs, runs)
    assert same["chaos_mm"]["mean"] == 0.0
    for name, r in same["measures"].items():
        assert r["within"] == 0.0 and (r["spearman"] == pytest.approx(1.0) or math.isnan(r["spearman"])), name
    reverse = two_run_reliability(runs, runs[::-1])
    values = [part_quality(t, t.pos[-1].double(), names=["draw_in_mean"])["draw_in_mean"] for t in runs]
    r = reverse["measures"]["draw_in_mean"]
    assert r["first"] == pytest.approx(values)
    assert len(set(values)) == 3 and sorted(values) in (values, values[::-1])  # the middle part lies between
    assert r["spearman"] == pytest.approx(-1.0)  # so the reversed run ranks them exactly backwards
    within = math.sqrt(sum((x - y) ** 2 for x, y in zip(values, values[::-1], strict=True)) / 3 / 2)
    assert r["within"] == pytest.approx(within)
    mean = [(x + y) / 2 for x, y in zip(values, values[::-1], strict=True)]
    assert r["range"] == pytest.approx(max(mean) - min(mean))
    with pytest.raises(ValueError, match="at least 3 settings"):
        two_run_reliability(runs[:2], runs[:2])


@pytest.mark.slow
def test_the_spread_command_reports_the_two_run_reliability(quick_sim, tmp_path, capsys):
    from torch_ampn.cli.data import main
    from torch_ampn.sim import simulate_batch

    (tmp_path / "train").mkdir()
    for t in simulate_batch(quick_sim, seeds=[5, 6, 7]):
        t.save(tmp_path / "train" / f"traj_{t.meta['seed']:06d}.pt")
    assert main(["spread", str(tmp_path), "--chaos", "3", "--json", str(tmp_path / "spread.json")]) == 0
    report = json.loads((tmp_path / "spread.json").read_text())
    reliability = report["reliability"]
    assert reliability["settings"] == 3 and set(reliability["measures"]) >= {"draw_in_mean", "wrinkle_rms"}
    assert reliability["chaos_mm"]["mean"] == pytest.approx(report["chaos_floor"]["mean"])
    out = capsys.readouterr().out
    assert "two runs of 3 settings" in out and "spearman" in out
