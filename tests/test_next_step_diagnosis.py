"""benchmarks/next_step_diagnosis.py: the constant-velocity step by hand, and the report on the tiny fit."""

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location(
        "next_step_diagnosis", ROOT / "benchmarks" / "next_step_diagnosis.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["next_step_diagnosis"] = module
    spec.loader.exec_module(module)
    return module


def test_constant_velocity_by_hand():
    pos = torch.tensor([0.0, 1.0, 3.0, 6.0]).reshape(4, 1, 1).expand(4, 1, 3)  # steps of 1, 2, 3
    pred = _load().constant_velocity(pos)[:, 0, 0].tolist()
    assert pred == [0.0, 0.0, 2.0, 5.0]  # x_1 = x_0 (no step before), x_2 = 1 + 1, x_3 = 3 + 2


def test_a_whole_trajectory_prediction_steps_from_the_true_states():
    true = torch.tensor([0.0, 1.0, 3.0]).reshape(3, 1, 1)
    pred = torch.tensor([0.0, 2.0, 2.5]).reshape(3, 1, 1)  # steps of 2 and 0.5
    stepped = _load().teacher_forced_steps(pred, true)[:, 0, 0].tolist()
    assert stepped == [0.0, 2.0, 1.5]  # 0 + 2, then 1 + 0.5


def test_the_report_of_a_checkpoint(tiny_data, tmp_path):
    from make_fixtures import TINY_CKPT

    diagnosis = _load()
    out = tmp_path / "diag.json"
    assert (
        diagnosis.main([str(TINY_CKPT), "--data-dir", str(tiny_data), "--restart", "2", "--out", str(out)])
        == 0
    )
    report = json.loads(out.read_text())
    rows = report["results"]["tiny"]
    assert report["restart"] == 2 and report["test_trajectories"] == 1 and out.with_suffix(".png").exists()
    mean = np.asarray(rows["mean_trajectory"]["rmse_per_step"])
    for r in rows.values():
        rmse, r2 = np.asarray(r["rmse_per_step"]), np.asarray(r["r2_per_step"])
        assert rmse[0] < 1e-6 and math.isnan(r2[0]) and len(rmse) == 7  # 6 saved steps; row 0 the given start
        np.testing.assert_allclose(
            r2[1:], 1 - rmse[1:] ** 2 / mean[1:] ** 2, rtol=1e-9
        )  # one test trajectory
    assert rows["mean_trajectory"]["r2"] == 0.0
    # the restart equals the truth up to its step; the first step of the rollout is the one step's
    assert rows["restart"]["rmse_per_step"][:3] == [0.0, 0.0, 0.0]
    assert rows["restart"]["rmse"] == pytest.approx(np.mean(rows["restart"]["rmse_per_step"][3:]))
    assert rows["rollout_zero_noise"]["rmse_per_step"][1] == pytest.approx(
        rows["one_step_zero_noise"]["rmse_per_step"][1]
    )
    assert (
        rows["noise_spread"]["rmse_per_step"][1] > 0
    )  # K = 1 reads N(0, 1) noise: another draw, another step
