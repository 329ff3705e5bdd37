"""`torch-ampn design` end to end on the tiny dataset: baseline and checkpoint, verify, bad input."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from torch_ampn.cli.design import main
from torch_ampn.design import MEASURES

TINY_CKPT = Path(__file__).parent / "data" / "tiny.ckpt"
BUDGET = ["--maxiter", "1", "--popsize", "2", "--map-points", "3", "--top", "2"]


def test_a_baseline_design_study_with_verification(tiny_data, tmp_path):
    out = tmp_path / "design"
    report = main([str(tiny_data), "--baseline", "mean_trajectory", "--measure", "draw_in_mean",
                   "--verify", "2", "--repeat", "1e-6", "--refine", "2", "--out", str(out),
                   *BUDGET])  # fmt: skip
    saved = json.loads((out / "design.json").read_text())
    assert saved["best"] == report["best"] and saved["measure"] == "draw_in_mean"
    assert report["search"]["evaluations"] == 2 * 2 * 4  # (maxiter + 1) generations x popsize x 4 settings
    assert report["best"]["objective"] == pytest.approx(report["best"]["measures"]["draw_in_mean"])
    assert min(t["objective"] for t in report["top"]) == report["best"]["objective"]
    assert [t["xdmf"] for t in report["top"]] == ["top_1.xdmf", "top_2.xdmf"]
    assert all((out / t["xdmf"]).is_file() for t in report["top"])
    assert all((out / f).is_file() for f in ("map.png", "verify.png", "fields.png"))
    v = report["verify"]
    assert v["rank"] == 1 + sum(s < v["chosen_simulated"] for s in v["random_simulated"])
    # the mean trajectory ignores the settings: the same predicted draw-in for all, no rank correlation
    assert np.ptp(v["random_predicted"] + [v["chosen_predicted"]]) < 1e-9 and v["spearman"] is None
    assert report["cost"]["simulator_seconds_per_setting"] > 0
    # every measure, the chosen setting first; the objective's Spearman is its measure's
    assert v["simulated_measures"]["draw_in_mean"] == [v["chosen_simulated"], *v["random_simulated"]]
    assert set(v["spearman_by_measure"]) == set(v["repeat_spearman_by_measure"]) == set(MEASURES)
    assert v["repeat"] == 1e-6 and len(v["repeat_measures"]["wrinkle_rms"]) == 2
    # the mean trajectory is flat in the settings: no descent step helps, nothing more to verify
    assert (
        report["refine"]["steps"] == 0
        and report["refine"]["objective"] == report["refine"]["start_objective"]
    )
    assert v["alternatives"] == {}


@pytest.mark.xdist_group("tiny_fit")
def test_a_checkpoint_design_study(tiny_data, tmp_path):
    report = main([str(tiny_data), "--checkpoint", str(TINY_CKPT), "--no-compile", "--measure",
                   "wrinkle_rms=1", "shear_max=0.01", "--out", str(tmp_path), *BUDGET])  # fmt: skip
    best = report["best"]
    weighted = best["measures"]["wrinkle_rms"] + 0.01 * best["measures"]["shear_max"]
    assert best["objective"] == pytest.approx(weighted)
    assert report["predictor"].startswith("surrogate")


def test_bad_input_ends_in_one_line(tiny_data, tmp_path, monkeypatch, capsys):
    from torch_ampn.cli.train import entry_point

    for args, message in [
        (["--baseline", "pod_gp", "--measure", "smoothness"], "--measure: measure must be among"),
        (["--checkpoint", str(tmp_path / "none.ckpt")], "no such checkpoint"),
        (["--baseline", "pod_gp", "--map", "force_0", "force_0"], "--map needs two different names"),
        (["--baseline", "pod_gp", "--verify", "4", "--runs", "0"], "--runs must be >= 1"),
        (["--baseline", "pod_gp", "--runs", "3"], "--runs 3 needs --verify N"),
        (["--baseline", "pod_gp", "--batch-size", "0"], "--batch-size must be >= 1"),
    ]:
        monkeypatch.setattr(
            sys, "argv", ["torch-ampn", "design", str(tiny_data), "--out", str(tmp_path), *args]
        )
        with pytest.raises(SystemExit) as exit_:
            entry_point()
        assert message in str(exit_.value) and "\n" not in str(exit_.value)
