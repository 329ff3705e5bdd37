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
