import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_hierarchy_levels_example_writes_a_figure(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "hierarchy_levels.py"),
            "--out",
            str(tmp_path),
            "--cache-dir",
            str(tmp_path / "cache"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={"MPLBACKEND": "Agg", "PATH": ""},
    )
    assert result.returncode == 0, result.stderr
    assert "HierarchicalData with 4 levels" in result.stdout
    png = tmp_path / "hierarchy_levels.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 20_000
    assert len(list((tmp_path / "cache").glob("hierarchy-*.pt"))) == 1


def _load_example(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_step_predictability_statistics_match_a_hand_computed_case():
    import math
    from types import SimpleNamespace

    import torch

    # Residuals per step: ply node 0 (1,0,0), (1,0,0), (0,1,0); ply node 1 (0,0,2), (0,0,-2),
    # (0,0,-2); node 2 is a tool with a large motion that must be ignored.
    du = torch.tensor(
        [
            [[1.0, 0, 0], [0, 0, 2], [50, 0, 0]],
            [[1.0, 0, 0], [0, 0, -2], [50, 0, 0]],
            [[0.0, 1, 0], [0, 0, -2], [50, 0, 0]],
        ]
    )
    pos = torch.cat([torch.zeros(1, 3, 3), du.cumsum(0)]) + 7.0
    traj = SimpleNamespace(displacement=lambda: pos - pos[:1], ply_mask=torch.tensor([True, True, False]))
    stats = _load_example("step_predictability").step_statistics(traj)
    torch.testing.assert_close(stats["zero"], torch.full((3,), math.sqrt(2.5), dtype=torch.float64))
    # constant velocity: step 2 errors 0 and 4 -> sqrt(8); step 3 errors sqrt(2) and 0 -> 1
    assert math.isnan(stats["const_vel"][0]) and math.isnan(stats["cos"][0])
    expected_const_vel = torch.tensor([math.sqrt(8.0), 1.0], dtype=torch.float64)
    torch.testing.assert_close(stats["const_vel"][1:], expected_const_vel)
    torch.testing.assert_close(stats["cos"][1:], torch.tensor([0.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(stats["max"], torch.full((3,), 2.0, dtype=torch.float64))


def test_step_predictability_names_an_empty_folder(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "step_predictability.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    assert str(tmp_path) in result.stderr and "no trajectory" in result.stderr


@pytest.mark.slow
def test_step_predictability_model_errors_agree_with_the_data_references(small_sim):
    """A 'model' that returns the truth errs 0; one that returns zero / the last residual
    reproduces the data-only ``zero`` / ``const_vel`` columns (computed independently)."""
    from dataclasses import replace
    from types import SimpleNamespace

    import torch

    from torch_ampn.data.dataset import HierarchyCache
    from torch_ampn.sim import simulate

    example = _load_example("step_predictability")
    # 5 saved steps over the same stroke: a trajectory of its own, not a prefix of small_runs[0]
    traj = simulate(replace(small_sim, num_steps=5), seed=3)
    hierarchy = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(traj)
    stats = example.step_statistics(traj)

    def fake(predict):
        return SimpleNamespace(surrogate=SimpleNamespace(contact=None, predict_residual=predict))

    truth = example.model_step_errors(fake(lambda data, g: data["l0"].target), traj, hierarchy)
    torch.testing.assert_close(truth, torch.zeros(5, dtype=torch.float64))
    zero = example.model_step_errors(
        fake(lambda data, g: torch.zeros_like(data["l0"].target)), traj, hierarchy
    )
    torch.testing.assert_close(zero, stats["zero"], rtol=1e-5, atol=1e-7)
    assert float(stats["zero"].max()) > 0.01  # the plies move, so the comparison has teeth
    last = example.model_step_errors(fake(lambda data, g: data["l0"].prev_disp), traj, hierarchy)
    torch.testing.assert_close(last[1:], stats["const_vel"][1:], rtol=1e-5, atol=1e-7)
