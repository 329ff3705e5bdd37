import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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
