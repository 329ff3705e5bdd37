"""benchmarks/under_load.py: busy processes end by themselves, a late run is killed, the table by hand."""

import importlib.util
import resource
import subprocess
import sys
from pathlib import Path

SPEC = importlib.util.spec_from_file_location(
    "under_load", Path(__file__).parents[1] / "benchmarks/under_load.py"
)
under_load = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(under_load)


def _row(workload, mechanism, busy, seconds=None):
    if seconds is None:
        return {
            "workload": workload,
            "mechanism": mechanism,
            "busy": busy,
            "timed_out": True,
            "wall_seconds": 60.2,
        }
    return {
        "workload": workload,
        "mechanism": mechanism,
        "busy": busy,
        "timed_out": False,
        "seconds": seconds,
    }


def test_the_table_shows_medians_ratios_and_timeouts():
    rows = [_row("train", "passive", 0, s) for s in (2.0, 3.0, 2.5)]
    rows += [_row("train", "passive", 1, s) for s in (5.0, 4.0, 9.0)]
    rows += [_row("train", "default", 0, 2.0), _row("train", "default", 1)]
    lines = under_load.table(rows).splitlines()
    assert lines[2] == "| train | passive | 2.50 | 5.00 (2.0x) | - | 3 |"
    assert lines[3] == "| train | default | 2.00 | > 60 (timed out) | - | 1 |"


def test_busy_processes_use_a_core_and_end_by_themselves():
    """It spins (CPU time, not wall time: a sleeping child would use a few hundredths of a second)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    busy = under_load.start_busy(1, limit=1.0)
    assert busy[0].wait(timeout=30) == 0  # ends by itself
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime > 0.3


def test_every_mechanism_names_only_controlled_variables():
    for env in under_load.MECHANISMS.values():
        assert set(env) <= set(under_load.CONTROLLED)
    assert under_load.MECHANISMS["package"] == {}  # what `import torch_ampn` chooses
    out = subprocess.run(
        [sys.executable, str(Path(under_load.__file__)), "--help"], capture_output=True, text=True
    )
    assert out.returncode == 0 and "--mechanisms" in out.stdout
