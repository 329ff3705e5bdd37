"""Setting-aware baselines across a family of parts: part parameters by hand, one baseline per ply
count checked on a synthetic family whose plies move as a known affine function of settings and part."""

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torch_ampn.baselines import (
    MeanTrajectory,
    NearestSetting,
    PerPlyCount,
    PODRegression,
    family_baselines,
    part_parameters,
    process_settings,
)
from torch_ampn.baselines.family import part_parameter_names
from torch_ampn.data import TrajectoryDataset

ANGLES = (0.0, 45.0, 90.0, -45.0)


def test_part_parameters_by_hand():
    traj = SimpleNamespace(meta={
        "part": {"shape": "single_dome", "dome_depth": 42.0, "dome_axes": (61.0, 52.0), "dome_centre": 0.0,
                 "dome_flat_top": 0.3, "ply_angles": (0.0, 45.0, 90.0)},
    })  # fmt: skip
    expected = [42.0, 61.0, 52.0, 0.0, 0.3, 2.0, 1.0, 0.0, -1.0, 0.0, 1.0, 0.0]  # cos 2θ, then sin 2θ
    torch.testing.assert_close(
        part_parameters(traj), torch.tensor(expected, dtype=torch.float64), atol=1e-15, rtol=0
    )
    assert len(part_parameter_names(3)) == 12 and part_parameter_names(3)[6] == "ply0_cos2theta"
    traj.meta["part"]["dome_exponent"] = 6.0  # a box
    assert part_parameters(traj)[5] == 6.0
    traj.meta = {"name": "traj_000007"}
    with pytest.raises(ValueError, match="traj_000007: meta has no 'part'"):
        part_parameters(traj)


def _family(templates, count: int, seed: int):
    """``count`` copies of each template with drawn settings and parts; the plies move by
    ``(t / T) * reshape(W f)`` from their start, ``f`` the settings and part parameters, and the
    punch and die nodes are shifted by the part's depth (another tool per part)."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    out = []
    for template in templates:
        plies = len(template.meta["part"]["ply_angles"])
        ply = template.ply_mask
        features = 4 + 6 + 2 * plies
        weights = torch.randn(int(ply.sum()) * 3, features, generator=torch.Generator().manual_seed(plies))
        steps = template.pos.size(0) - 1
        for k in range(count):
            traj = copy.deepcopy(template)
            angles = [ANGLES[int(i)] for i in torch.randint(4, (plies,), generator=g)]
            traj.meta["part"] = {
                "shape": "single_dome" if k % 2 else "double_dome",
                "dome_depth": 40 + 15 * float(rand(())),
                "dome_axes": (60 + 15 * float(rand(())), 50 + 15 * float(rand(()))),
                "dome_centre": 45 + 15 * float(rand(())), "dome_flat_top": 0.25 + 0.2 * float(rand(())),
                "ply_angles": tuple(angles),
            }  # fmt: skip
            traj.meta["gripper_edge_fraction"] = (0.15 + 0.7 * rand(2)).tolist()
            traj.gripper_force = (100 * rand(2)).float()
            traj.meta["name"] = f"part_{plies}_{k}"
            f = torch.cat([process_settings(traj), part_parameters(traj)])
            move = (weights.double() @ f).reshape(-1, 3) * 1e-2  # [P, 3]
            pos = template.pos[0].double().repeat(steps + 1, 1, 1)
            pos[:, ply] += torch.linspace(0, 1, steps + 1, dtype=torch.float64)[:, None, None] * move
            pos[:, ~ply, 2] -= traj.meta["part"]["dome_depth"]
            traj.pos = pos.float()
            out.append(traj)
    return out


@pytest.fixture(scope="module")
def family(tiny_family):
    data = TrajectoryDataset(tiny_family, "train")
    two, three = data[0], data[1]  # 2 and 3 plies
    assert len(two.meta["part"]["ply_angles"]) == 2 and len(three.meta["part"]["ply_angles"]) == 3
    return _family([two, three], 24, seed=0), _family([two, three], 3, seed=1)


def test_a_linear_regression_per_ply_count_recovers_an_affine_family(family):
    train, test = family
    linear = PerPlyCount(lambda: PODRegression("linear", num_components=None)).fit(train)
    assert sorted(linear.baselines) == [2, 3] and all(b.parts for b in linear.baselines.values())
    predicted = linear.predict_many(test)
    for traj, pos in zip(test, predicted, strict=True):
        torch.testing.assert_close(
            pos, traj.pos, atol=2e-4, rtol=0
        )  # the plies by the fit, the tools its own
    assert torch.equal(linear.predict(test[4]), predicted[4])


def test_the_mean_and_the_nearest_per_ply_count_by_hand(family):
    train, test = family
    mean = PerPlyCount(MeanTrajectory).fit(train)
    nearest = PerPlyCount(NearestSetting).fit(train)
    for traj in test:
        plies = len(traj.meta["part"]["ply_angles"])
        group = [t for t in train if len(t.meta["part"]["ply_angles"]) == plies]
        ply = traj.ply_mask
        by_hand = torch.stack([t.pos[:, ply].double() for t in group]).mean(0)
        torch.testing.assert_close(mean.predict(traj)[:, ply].double(), by_hand, atol=1e-5, rtol=0)
        x = np.stack([torch.cat([process_settings(t), part_parameters(t)]).numpy() for t in group])
        scale = np.where(x.std(0) > 0, x.std(0), 1.0)
        z = (torch.cat([process_settings(traj), part_parameters(traj)]).numpy() - x.mean(0)) / scale
        best = int((((x - x.mean(0)) / scale - z) ** 2).sum(1).argmin())
        assert torch.equal(nearest.predict(traj)[:, ply], group[best].pos[:, ply])


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")  # GP length scales at bounds
def test_a_part_no_parametric_surrogate_can_place_is_refused_in_one_line(family):
    train, test = family
    pod_gp = family_baselines()["pod_gp"].fit(train)
    assert all(torch.isfinite(p).all() for p in pod_gp.predict_many(test))
    box = copy.deepcopy(test[0])
    box.meta["part"] = {**box.meta["part"], "shape": "box", "dome_exponent": 6.0, "dome_centre": 0.0}
    with pytest.raises(
        ValueError, match=r"a 'box' part; the 2-ply training parts were \['double_dome', 'single_dome'\]"
    ):
        pod_gp.predict(box)
    four = copy.deepcopy(test[0])
    four.meta["part"] = {**four.meta["part"], "ply_angles": (0.0, 0.0, 0.0, 0.0)}
    with pytest.raises(
        ValueError, match=r"part_2_0: a part of 4 plies; the baselines were fitted on parts of \[2, 3\]"
    ):
        pod_gp.predict(four)
    # without the part's parameters, the tools that differ between parts are another mesh
    with pytest.raises(ValueError, match="starts elsewhere"):
        MeanTrajectory().fit([t for t in train if len(t.meta["part"]["ply_angles"]) == 2])
    assert math.isfinite(float(pod_gp.predict(test[0]).sum()))


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_a_test_report_leaves_out_the_baselines_that_cannot_place_a_part(family, tmp_path):
    """torch-ampn test on a family: a box part gets NaN from every setting-aware baseline, which the
    summary then leaves out (the trivial ones stay); the reason is kept for the printout."""
    from torch_ampn.baselines import fit_setting_baselines
    from torch_ampn.data import HierarchyCache
    from torch_ampn.training.baseline_rollouts import BaselineRollouts
    from torch_ampn.training.report import TestReport

    train, test = family
    setting, reason = fit_setting_baselines(train)
    assert reason is None and all(isinstance(b, PerPlyCount) for b in setting.values())
    rollouts = BaselineRollouts([3.0], setting)
    box = copy.deepcopy(test[0])
    box.meta["part"] = {**box.meta["part"], "shape": "box", "dome_exponent": 6.0, "dome_centre": 0.0}
    report = TestReport(tmp_path)
    for k, traj in enumerate([test[0], box]):
        item = SimpleNamespace(trajectory=traj, hierarchy=HierarchyCache(None, max_levels=2)(traj))
        curves = rollouts.rmse(item)
        placed = k == 0
        assert all(bool(torch.isfinite(curves[n]).all()) == placed for n in setting)
        assert torch.isfinite(curves["static"]).all() and torch.isfinite(curves["rigid_r3"]).all()
        model = curves["static"] * 0.5
        report.rows.append({"trajectory": f"t{k}", "model": float(model[1:].mean()), "rollout_seconds": 1.0,
                            **{n: float(c[1:].mean()) for n, c in curves.items()}})  # fmt: skip
        for name, curve in {"model": model, **curves}.items():
            report.curves.setdefault(name, []).append(curve)
    assert set(rollouts.refused) == set(setting) and "a 'box' part" in rollouts.refused["pod_gp"]
    summary = report.summary()
    assert "setting_baseline" not in summary and "setting_effect_r2" not in summary
    assert summary["static_rmse"] == pytest.approx((report.rows[0]["static"] + report.rows[1]["static"]) / 2)
    # a test set of placeable parts keeps them all
    report.rows, report.curves = report.rows[:1], {n: c[:1] for n, c in report.curves.items()}
    assert report.summary()["setting_baseline"] in setting
