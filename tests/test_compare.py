"""benchmarks/compare.py end to end on a tiny budget: cells, the report's rows, resuming, a killed cell."""

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml

pytest.importorskip("lightning")

from helpers import checkpoint_steps, eager_fast_rollout, tiny_cli_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _load_compare():
    spec = importlib.util.spec_from_file_location("compare", ROOT / "benchmarks" / "compare.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["compare"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_data):
    root = tmp_path_factory.mktemp("compare")
    config = tiny_cli_config(data={"generate": False})
    (root / "tiny.yaml").write_text(yaml.safe_dump(config))
    args = [
        "--config", str(root / "tiny.yaml"), "--data-dir", str(tiny_data), "--steps", "3",
        "--seeds", "0", "--results", str(root / "results"), "--workdir", str(root / "work"),
        "--simulator-mode", "eager",
    ]  # fmt: skip
    return root, args


@pytest.fixture(scope="module")
def two_cells(setup):
    """``compare.py`` run once with the AMPN and ROBIN K = 5 cells: ``(root, args, compare, cells)``.

    The fast path runs eagerly (the timings' table is checked here, compiling in test_fast_rollout.py).
    """
    root, args = setup
    compare = _load_compare()
    with pytest.MonkeyPatch.context() as monkeypatch:
        eager_fast_rollout(monkeypatch)
        assert compare.main([*args, "--variants", "ampn", "robin5"]) == 0
    results = root / "results"
    cells = {v: json.loads((results / f"{v}_seed0.json").read_text()) for v in ("ampn", "robin5")}
    return root, args, compare, cells


#: The tests of one ``two_cells`` run share a worker (xdist) and run in this file's order.
two_cells_group = pytest.mark.xdist_group("compare_two_cells")


@pytest.mark.slow
@two_cells_group
def test_two_cells_hold_their_tests_numbers(two_cells):
    root, _, _, cells = two_cells
    results = root / "results"
    for variant, cell in cells.items():
        summary = json.loads((root / "work" / f"{variant}_seed0" / "test" / "test_summary.json").read_text())
        assert cell["rmse"] == pytest.approx(summary["rollout_rmse"])  # the test's own number
        per_trajectory = list(cell["rmse_per_trajectory"].values())
        assert cell["rmse"] == pytest.approx(sum(per_trajectory) / len(per_trajectory))
        curve = cell["rmse_over_time"]["model"]
        assert (
            len(curve) == 7 and curve[0] == 0 and sum(curve[1:]) / 6 == pytest.approx(cell["rmse"], rel=1e-5)
        )
        assert cell["speedup"] == pytest.approx(cell["simulator"]["fastest"] / cell["rollout_seconds"])
        assert cell["contact_edges_per_step"]["fine"] > 0 and cell["steps"] == 3
        states = torch.load(results / f"{variant}_seed0.states.pt", weights_only=True)
        assert states["steps"] == [4, 5, 6] and states["pos"].shape[0] == 3
    assert cells["robin5"]["changes"] == {"model.diffusion_steps": 5}
    assert cells["ampn"]["layers"] == cells["robin5"]["layers"] == 5


@pytest.mark.slow
@two_cells_group
def test_the_report_has_a_row_per_variant_and_the_figures(two_cells):
    root, _, _, cells = two_cells
    results = root / "results"
    # one row per variant (mean over the seeds present), the references and baselines
    table = json.loads((results / "table.json").read_text())["rows"]
    aware = ["mean_trajectory", "nearest_setting", "linear_settings", "pod_gp"]
    assert [r["variant"] for r in table] == ["ampn", "robin5", "simulator_rerun", "static", "rigid", *aware]
    assert table[0]["rmse"] == pytest.approx(cells["ampn"]["rmse"]) and table[0]["seeds"] == [0]
    assert table[2]["rmse"] < table[3]["rmse"]  # the simulator repeats itself better than "no motion"
    # the setting-aware rows: the means of a cell's test table, with their R^2 from its summary
    test_dir = root / "work" / "ampn_seed0" / "test"
    summary = json.loads((test_dir / "test_summary.json").read_text())
    rows = list(csv.DictReader(open(test_dir / "test_rmse.csv")))
    by_variant = {r["variant"]: r for r in table}
    for name in aware:
        assert by_variant[name]["rmse"] == pytest.approx(sum(float(r[name]) for r in rows) / len(rows))
        assert by_variant[name]["r2"] == pytest.approx(summary[f"{name}_r2"])
    assert by_variant["mean_trajectory"]["r2"] == 0.0
    assert table[0]["r2"] == pytest.approx(summary["setting_effect_r2"])
    markdown = (results / "table.md").read_text()
    assert "ROBIN, K = 5" in markdown and "missing" not in markdown
    assert "| POD + Gaussian process on the settings (baseline) |" in markdown
    for name in ("compare_rmse_over_time.png", "compare_fig2.png", "compare_fig3.png"):
        assert (results / "figures" / name).is_file(), name


@pytest.mark.slow
@two_cells_group
def test_a_report_of_some_variants_keeps_the_rows_of_the_others(two_cells):
    root, args, compare, cells = two_cells
    results = root / "results"
    assert compare.main([*args, "--variants", "robin5", "--report", "--no-figures"]) == 0
    rows = {r["variant"]: r for r in json.loads((results / "table.json").read_text())["rows"]}
    assert list(rows)[:2] == ["robin5", "ampn"]  # the named variants first, then the others found
    assert rows["ampn"]["rmse"] == pytest.approx(cells["ampn"]["rmse"])


@pytest.mark.slow
@two_cells_group
def test_a_rerun_skips_done_cells_and_a_failed_cell_writes_nothing(two_cells, capsys):
    root, args, compare, cells = two_cells
    results = root / "results"
    # a second run finds both cells done: nothing is fitted again
    logs = {v: (root / "work" / f"{v}_seed0" / "log.txt").stat().st_mtime for v in cells}
    simulator = (results / "simulator.json").stat().st_mtime
    capsys.readouterr()
    assert compare.main([*args, "--variants", "ampn", "robin5", "--no-figures"]) == 0
    assert "2 cells done before, skipped" in capsys.readouterr().out
    assert {v: (root / "work" / f"{v}_seed0" / "log.txt").stat().st_mtime for v in cells} == logs
    # a cell that fails leaves no result, and the run goes on with the next one
    broken = [*args, "--variants", "radius", "ampn", "--no-figures", "--set", "model.contact_mode", "none"]
    assert compare.main(broken) == 1
    printed = capsys.readouterr().out
    assert "the embedded simulator: measured before (simulator.json)" in printed  # same data, not again
    assert (results / "simulator.json").stat().st_mtime == simulator
    assert "radius seed 0: FAILED, no result written" in printed
    assert "1 cell(s) failed: radius_seed0" in printed
    assert not (results / "radius_seed0.json").exists()


@pytest.mark.slow
@two_cells_group
def test_timings_feed_the_table_and_a_variant_without_cells_is_missing(two_cells, monkeypatch):
    root, args, compare, _ = two_cells
    results = root / "results"
    eager_fast_rollout(monkeypatch)
    # side-by-side timings from the saved weights: the table's rollout column comes from them
    assert (results / "ampn_seed0.ckpt").is_file()
    assert compare.main([*args, "--variants", "ampn", "--timings", "--repeats", "1", "--no-figures"]) == 0
    timed = json.loads((results / "timings.json").read_text())
    entry = timed["variants"]["ampn"]
    assert entry["checkpoint"] == "ampn_seed0.ckpt"
    assert entry["plain_seconds"] > 0 and entry["fast_seconds"] > 0
    assert entry["fast_speedup"] == pytest.approx(timed["simulator_seconds"] / entry["fast_seconds"])
    row = json.loads((results / "table.json").read_text())["rows"][0]
    assert row["rollout_seconds"] == entry["fast_seconds"] and row["timed"] == timed["date"]
    # the report marks a variant without cells as missing
    assert compare.main([*args, "--variants", "ampn", "flat", "--report", "--no-figures"]) == 0
    assert "| flat MeshGraphNet (1 level) | missing |" in (results / "table.md").read_text()


@pytest.mark.slow
def test_a_killed_cell_leaves_no_result(setup):
    root, args = setup
    cmd = [sys.executable, str(ROOT / "benchmarks" / "compare.py"), *args, "--variants", "flat"]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    log = root / "work" / "flat_seed0" / "log.txt"
    deadline = time.monotonic() + 300
    while not (log.exists() and "fit" in log.read_text()) and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)  # inside the fit
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert log.exists(), "the cell never started"
    results = root / "results"
    assert not (results / "flat_seed0.json").exists() and not (results / "flat_seed0.states.pt").exists()
    assert not list(results.glob(".*.tmp"))


def test_cells_keep_the_best_and_the_last_step(tmp_path):
    """A cell's ``last.ckpt`` follows every validation (it is resumed from), ``best.ckpt`` the lowest RMSE."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    entries = _load_compare().checkpoint_callbacks(tmp_path)
    assert {e["class_path"] for e in entries} == {"lightning.pytorch.callbacks.ModelCheckpoint"}
    checkpoints = [ModelCheckpoint(**e["init_args"]) for e in entries]
    assert checkpoint_steps(checkpoints, tmp_path) == (2, 6)


@pytest.mark.parametrize(
    ("steps", "interval", "expected"),
    [(3000, 2000, 1500), (1000, 2000, 1000), (10000, 2000, 2000), (12000, 2000, 2000), (7, 3, 1), (6, 4, 3)],
)
def test_the_cells_validate_at_their_last_step(steps, interval, expected):
    """best.ckpt is written at validations: the last one must be the fit's last step (a 3,000-step cell
    validated every 2,000 was tested with its step-2,000 weights), at least as often as asked."""
    compare = _load_compare()
    got = compare.validation_interval(steps, interval)
    assert got == expected and steps % got == 0 and got <= interval
