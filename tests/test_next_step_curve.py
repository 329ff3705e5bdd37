"""benchmarks/next_step_curve.py: the power law, its extrapolation and the cells it reads."""

import importlib.util
import json
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("next_step_curve", ROOT / "benchmarks" / "next_step_curve.py")
curve = importlib.util.module_from_spec(spec)
spec.loader.exec_module(curve)


def _cell(path: Path, steps: int, rmse: float, seed: int = 0) -> Path:
    baselines = {"linear_settings_rmse": 0.5, "nearest_setting_rmse": 0.8, "mean_trajectory_rmse": 1.2}
    cell = {"rmse": rmse, "steps": steps, "seed": seed, "setting_effect_r2": 0.5, "fit_seconds": 10.0}
    path.write_text(json.dumps({**cell, "baselines": baselines}))
    return path


def test_power_law_through_two_points_and_where_it_reaches_a_target():
    # RMSE = 8 steps^-0.5: 0.8 at 100 steps, 0.4 at 400; 0.2 at 1,600 steps
    points = [{"steps": 100, "rmse": 0.8}, {"steps": 400, "rmse": 0.4}]
    law = curve.power_law(points)
    assert law["a"] == pytest.approx(8.0) and law["c"] == pytest.approx(0.5)
    assert curve.steps_to_reach(law, 0.2) == pytest.approx(1600.0)
    # the last two points only, unless told otherwise: an early point off the line does not count
    off = [{"steps": 10, "rmse": 100.0}, *points]
    assert curve.power_law(off)["c"] == pytest.approx(0.5)
    assert curve.power_law(off, fit_all=True)["c"] > 0.5
    assert curve.power_law(points[:1]) is None
    assert curve.steps_to_reach({"a": 1.0, "c": -0.1}, 0.2) is None  # a rising curve reaches nothing


def test_cells_make_series_with_step_overrides(tmp_path):
    a = _cell(tmp_path / "a.json", 3000, 1.6)
    b = _cell(tmp_path / "b.json", 3000, 0.8)
    out = tmp_path / "curve.json"
    args = ["--cell", f"x={a}@1000", "--cell", f"x={b}", "--out", str(out)]
    assert curve.main(args) == 0
    assert json.loads(out.read_text())["series"]["x"]["power_law"] is None  # two step counts: no law
    assert curve.main([*args, "--min-points", "2"]) == 0
    result = json.loads(out.read_text())
    series = result["series"]["x"]
    assert [p["steps"] for p in series["points"]] == [1000, 3000]
    assert series["points"][0]["fit_seconds"] is None  # the 3,000-step fit's time is not the point's
    assert series["power_law"]["c"] == pytest.approx(math.log(2) / math.log(3))
    # 1.6 (s / 1000)^-c = 0.5 at s = 1000 * 3.2^(1/c)
    expected = 1000 * 3.2 ** (math.log(3) / math.log(2))
    assert series["steps_to_linear_regression"] == pytest.approx(expected, rel=1e-9)
    assert result["baselines"]["linear regression on the settings"] == 0.5
    assert out.with_suffix(".png").stat().st_size > 0


def test_a_cell_that_is_not_a_compare_cell_is_named(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"rmse": 1.0}))
    with pytest.raises(SystemExit, match=r"bad\.json: field 'steps' missing"):
        curve.main(["--cell", f"x={bad}", "--out", str(tmp_path / "c.json")])
    with pytest.raises(SystemExit):  # argparse: LABEL=PATH expected
        curve.main(["--cell", "no-label", "--out", str(tmp_path / "c.json")])
