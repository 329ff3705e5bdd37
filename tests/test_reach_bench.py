"""benchmarks/reach end to end on a tiny budget: equal parameter counts, a cell, resuming, the table."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "reach"))

from networks import AMPN_VARIANTS, build, count, layer_calls  # noqa: E402
from report import collect, markdown, summarise  # noqa: E402


@pytest.mark.parametrize("levels", [3, 4])
def test_every_network_matches_the_ampn_parameter_count_within_5_percent(levels):
    reference = count(build("ampn", 4, 1, 3, levels, 32))
    for name in ("flat", "flat_deep", "graph_unet", *AMPN_VARIANTS):
        assert abs(count(build(name, 4, 1, 3, levels, 32)) / reference - 1) < 0.05, name
    deep = build("flat_deep", 4, 1, 3, levels, 32).model
    assert deep.num_levels == 1 and deep.num_layers == layer_calls(levels)  # as deep as the V-cycle's calls
    # by hand: Pre 2, Down 1, Up 1, Post 2 on every level above the coarsest; Pre, Solve 4, Post there
    assert layer_calls(levels) == (levels - 1) * 6 + 8


@pytest.mark.slow
def test_a_cell_trains_tests_resumes_and_reports(tmp_path):
    env = {**os.environ, "AMPN_REACH_DATA": str(tmp_path / "data"), "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable, str(ROOT / "benchmarks" / "reach" / "run.py"), "--problems", "laplace",
        "--sizes", "300", "--networks", "ampn", "flat", "--seeds", "0", "--budget", "3",
        "--out", str(tmp_path / "cells"),
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=tmp_path, env=env, capture_output=True)
    cells = sorted((tmp_path / "cells").glob("*.json"))
    assert [c.name for c in cells] == ["laplace_300_ampn_s0.json", "laplace_300_flat_s0.json"]
    cell = json.loads(cells[0].read_text())
    assert cell["steps"] >= 1 and 0 < cell["rel_l2"] < 10 and cell["train_meshes"] == 64
    assert sum(b["nodes"] for b in cell["by_hop"]) > 0 and cell["by_hop"][0]["hops_from"] == 0
    before = cells[0].stat().st_mtime_ns
    subprocess.run(cmd, check=True, cwd=tmp_path, env=env, capture_output=True)  # resumes: nothing to do
    assert cells[0].stat().st_mtime_ns == before
    rows = summarise(collect(tmp_path / "cells"))
    table = markdown(rows)
    assert "| laplace |" in table and "AMPN" in table and len(rows) == 2
