"""benchmarks/family.py end to end on a tiny budget: both cells, one at a time, the table, resuming."""

import contextlib
import csv
import importlib.util
import io
import json
import shutil
import sys
from pathlib import Path

import pytest
import yaml

pytest.importorskip("lightning")

from helpers import tiny_cli_config  # noqa: E402
from make_fixtures import DEEP, TINY_FAMILY, TINY_FAMILY_DEEP  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _load_family_bench():
    spec = importlib.util.spec_from_file_location("family_bench", ROOT / "benchmarks" / "family.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["family_bench"] = module
    spec.loader.exec_module(module)
    return module


def _config(simulator: dict, **model) -> dict:
    return tiny_cli_config(model=model, data={"simulator": simulator})


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_data):
    """Tiny single-part and family configs on copies of the committed datasets (tests/data)."""
    from torch_ampn.testing import SMALL_SIMULATOR

    root = tmp_path_factory.mktemp("family_bench")
    shutil.copytree(TINY_FAMILY, root / "family")  # the benchmark writes family_seen/ beside it
    shutil.copytree(TINY_FAMILY_DEEP, root / "family_deep")  # the extrapolation set "deep"
    single = _config(SMALL_SIMULATOR)
    single["data"].update(num_train=2, num_val=1, num_test=1)
    fam = _config(SMALL_SIMULATOR, component_encoding="stack", num_components=5)
    fam["data"]["family"] = {"num_plies": [2, 3]}
    (root / "single.yaml").write_text(yaml.safe_dump(single))
    (root / "family.yaml").write_text(yaml.safe_dump(fam))
    args = [
        "--single-config", str(root / "single.yaml"), "--family-config", str(root / "family.yaml"),
        "--single-data", str(tiny_data), "--family-data", str(root / "family"),
        "--num-train", "3", "--num-val", "1", "--num-test", "2",
        "--extrapolation", f"deep={json.dumps(DEEP)}", "--num-extrapolation", "2",
        "--num-seen", "2",
        "--steps", "3", "--results", str(root / "results"), "--workdir", str(root / "work"),
    ]  # fmt: skip
    return root, args


def _test_rows(folder: Path) -> list[dict]:
    with (folder / "test_rmse.csv").open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def family_cell(setup):
    """The family cell run alone: ``(root, args, bench, printed)``."""
    root, args = setup
    bench = _load_family_bench()
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert bench.main([*args, "--cells", "family"]) == 0
    return root, args, bench, out.getvalue()


@pytest.fixture(scope="module")
def both_cells(family_cell):
    """Then the whole benchmark: ``(root, args, bench, printed, single cell, family cell)``."""
    root, args, bench, _ = family_cell
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert bench.main(args) == 0
    results = root / "results"
    single = json.loads((results / "single_seed0.json").read_text())
    family = json.loads((results / "family_seed0.json").read_text())
    return root, args, bench, out.getvalue(), single, family


#: The tests of one benchmark run share a worker (xdist) and run in this file's order.
bench_group = pytest.mark.xdist_group("family_bench")


@pytest.mark.slow
@bench_group
def test_one_cell_alone_writes_no_report(family_cell):
    root, _, _, printed = family_cell
    results = root / "results"
    assert (results / "family_seed0.json").exists() and not (results / "single_seed0.json").exists()
    assert not (results / "table.json").exists() and "report: waits" in printed


@pytest.mark.slow
@bench_group
def test_both_cells_share_the_budget_and_test_every_set(both_cells):
    root, _, _, printed, single, family = both_cells
    assert "family: done before, skipped" in printed
    assert (
        single["steps"] == family["steps"] == 3 and single["seed"] == family["seed"] == 0
    )  # the same budget
    assert list(single["sets"]) == ["single"] and list(family["sets"]) == ["inside", "seen", "deep"]
    assert family["num_train"] == 3 and family["sets"]["deep"]["family_changes"] == DEEP
    rows = {name: _test_rows(folder) for name, folder in _test_folders(root).items()}
    assert len(rows["single"]) == 1 and len(rows["inside"]) == 2 and len(rows["deep"]) == 2
    # the seen set is the first two training trajectories, byte for byte
    train = sorted((root / "family" / "train").glob("*.pt"))[:2]
    assert [r["trajectory"] for r in rows["seen"]] == [f.stem for f in train]
    for f in train:
        assert (root / "family_seen" / "test" / f.name).read_bytes() == f.read_bytes()
    assert not list((root / "family_seen").rglob("*.tmp"))
    depths = [float(r["part"].rsplit(", ", 1)[1].removesuffix(" mm")) for r in rows["deep"]]
    assert all(55 <= d <= 60 for d in depths)  # the extrapolation set is the deeper domes


def _test_folders(root: Path) -> dict[str, Path]:
    """Every set is its own test folder."""
    return {
        "single": root / "work" / "single_seed0" / "test",
        "inside": root / "work" / "family_seed0" / "test",
        "seen": root / "work" / "family_seed0" / "test_seen",
        "deep": root / "work" / "family_seed0" / "test_deep",
    }


@pytest.mark.slow
@bench_group
def test_the_table_holds_each_sets_mean_and_every_test_part(both_cells):
    root = both_cells[0]
    results = root / "results"
    folders = _test_folders(root)
    rows = {name: _test_rows(folder) for name, folder in folders.items()}
    table = json.loads((results / "table.json").read_text())
    by_set = {r["set"]: r for r in table["rows"]}
    assert list(by_set) == ["single", "inside", "seen", "deep"]
    for name, set_rows in rows.items():  # RMSE = the mean of the per-trajectory rows, parts named
        mean = sum(float(r["model"]) for r in set_rows) / len(set_rows)
        summary = json.loads((folders[name] / "test_summary.json").read_text())
        row = by_set[name]
        assert row["rmse"] == pytest.approx(mean, rel=1e-6) and row["parts"] == len(set_rows)
        assert row["below_baseline"] == pytest.approx(summary["baseline_rmse"] / mean, rel=1e-6)
        assert row["vs_single"] == pytest.approx(mean / by_set["single"]["rmse"], rel=1e-6)
    markdown = (results / "table.md").read_text()
    for r in rows["inside"] + rows["deep"]:
        assert f"| {r['trajectory']} | {r['part']} |" in markdown  # one row per test part
    assert "missing" not in markdown
    assert (results / "best_and_worst.png").stat().st_size > 10_000


@pytest.mark.slow
@bench_group
def test_a_rerun_fits_nothing_again(both_cells, capsys):
    root, args, bench, *_ = both_cells
    logs = {c: (root / "work" / f"{c}_seed0" / "log.txt").stat().st_mtime for c in ("single", "family")}
    capsys.readouterr()
    assert bench.main([*args, "--no-figures"]) == 0
    printed = capsys.readouterr().out
    assert "single: done before, skipped" in printed and "family: done before, skipped" in printed
    assert {c: (root / "work" / f"{c}_seed0" / "log.txt").stat().st_mtime for c in logs} == logs


def test_best_and_worst_parts_by_error_relative_to_the_baseline():
    bench = _load_family_bench()

    def part(name: str, model: float, baseline: float) -> dict:
        return {"trajectory": name, "part": "", "model": model, "best_baseline": baseline}

    family = {
        "sets": {
            "inside": {"trajectories": [part("a", 1.0, 2.0), part("b", 1.0, 5.0), part("c", 2.0, 2.5)]},
            "seen": {"trajectories": [part("s", 0.1, 9.0), part("t", 9.0, 1.0)]},  # in neither group
            "deep": {"trajectories": [part("d", 3.0, 4.0)]},
            "angle": {"trajectories": [part("e", 1.0, 4.0), part("f", 2.0, 8.0)]},
        }
    }
    # ratios inside: a 0.5, b 0.2, c 0.8; outside: d 0.75, e 0.25, f 0.25 (first of equals)
    picked = [(s, t["trajectory"]) for s, t in bench.best_and_worst(family)]
    assert picked == [("inside", "b"), ("inside", "c"), ("angle", "e"), ("deep", "d")]


def test_a_malformed_extrapolation_is_refused_in_one_line(capsys):
    bench = _load_family_bench()
    with pytest.raises(SystemExit):
        bench.parse_args(["--extrapolation", "deeper"])
    assert "--extrapolation deeper: not NAME=JSON with a mapping" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.parse_args(["--extrapolation", 'seen={"dome_depth": [55, 60]}'])
    assert "the name 'seen' is taken" in capsys.readouterr().err
