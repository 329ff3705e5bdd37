"""Fixtures shared by several test files (pure helpers live in ``torch_ampn.testing``).

Imports are inside the fixtures, so that collecting a test file that uses none stays cheap.
"""

import collections
import os
import sys
from pathlib import Path

import pytest

# The benchmark scripts import their helpers (``device_info``) from their own folder, which is on
# ``sys.path`` when a script runs; the tests that load a script by its path need it there too.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

# Compiled rollout steps get Inductor's Python wrapper in the tests (and in the fits and notebooks
# they start, which inherit the environment): the C++ wrapper, FastRollout's default for small
# steps, costs about half a minute of extra compile per mesh and batch size, and most tests roll a
# mesh out only once. The tests of the default rule unset it (tests/test_fast_rollout.py).
os.environ.setdefault("TORCHINDUCTOR_CPP_WRAPPER", "0")


@pytest.fixture(scope="session")
def small_sim():
    """The small stamp-forming setting (``torch_ampn.testing.SMALL_SIMULATOR``: 6 saved steps)."""
    from torch_ampn.sim import StampFormingConfig
    from torch_ampn.testing import SMALL_SIMULATOR

    return StampFormingConfig.from_dict(SMALL_SIMULATOR)


@pytest.fixture(scope="session")
def quick_sim():
    """``small_sim`` for a quarter of the stroke (``torch_ampn.testing.QUICK_SIMULATOR``): 4x quicker."""
    from torch_ampn.sim import StampFormingConfig
    from torch_ampn.testing import QUICK_SIMULATOR

    return StampFormingConfig.from_dict(QUICK_SIMULATOR)


@pytest.fixture(scope="session")
def small_runs(small_sim):
    """Seeds 3 and 4 of ``small_sim``, simulated once per session: read them, never modify them."""
    from torch_ampn.sim import simulate_batch

    return simulate_batch(small_sim, seeds=[3, 4])


def _copy_of(tmp_path_factory, source):
    """A copy of the committed folder ``source`` (reading a dataset writes a hierarchy cache into it)."""
    import shutil

    copy = tmp_path_factory.mktemp(source.name) / "data"
    shutil.copytree(source, copy)
    return copy


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """A copy of the committed tiny dataset (``tests/data/tiny``: 2/1/1 trajectories of ``small_sim``).

    Made by ``tests/make_fixtures.py``; ``tests/test_fixtures.py`` checks that it still makes it.
    """
    from make_fixtures import TINY_DATA

    return _copy_of(tmp_path_factory, TINY_DATA)


@pytest.fixture(scope="session")
def tiny_family(tmp_path_factory):
    """A copy of the committed tiny family dataset (``tests/data/tiny_family``: parts of 2 and 3 plies)."""
    from make_fixtures import TINY_FAMILY

    return _copy_of(tmp_path_factory, TINY_FAMILY)


@pytest.fixture(scope="session")
def tiny_fit(tmp_path_factory, tiny_data):
    """The test run's one fit (``make_fixtures.fit_config``: 6 steps): ``(data folder, output folder)``.

    The output folder holds ``ckpt/last.ckpt`` (steps 3 and 6), ``logs/metrics.csv`` and
    ``reports/``; tests read it and write elsewhere. Tests that use it carry
    ``@pytest.mark.xdist_group("tiny_fit")``, so that ``pytest -n`` fits once, in one worker.
    """
    from make_fixtures import make_checkpoint

    last = make_checkpoint(tmp_path_factory.mktemp("tiny_fit"), tiny_data)  # out/ckpt/last.ckpt
    return tiny_data, last.parent.parent


def _group(item) -> str | None:
    mark = item.get_closest_marker("xdist_group")
    return None if mark is None else (mark.args[0] if mark.args else mark.kwargs.get("name"))


def _movable(item, group_sizes: dict) -> bool:
    """Whether ``item`` can run out of its file's order: in no xdist group of several tests (a
    group's tests run in file order) and using no module-scoped fixture (moving it would set that
    fixture up once more)."""
    group = _group(item)
    if group is not None and group_sizes[group] > 1:
        return False
    info = getattr(item, "_fixtureinfo", None)
    defs = info.name2fixturedefs.values() if info is not None else ()
    return all(d.scope != "module" for chain in defs for d in chain)


def pytest_collection_modifyitems(config, items):
    """The notebooks (``--nbmake``) count as slow: each simulates, trains and rolls out.

    Slow tests that can move run first (longest first, as a scheduler of unequal jobs should):
    ``pytest -n`` hands tests out in this order, and a long test handed out last keeps one
    worker busy while the others wait. Everything else keeps its order.
    """
    for item in items:
        if item.nodeid.endswith(".ipynb"):
            item.add_marker(pytest.mark.slow)
    group_sizes = collections.Counter(_group(item) for item in items)
    slow = [i for i in items if i.get_closest_marker("slow") is not None and _movable(i, group_sizes)]
    first = sorted(slow, key=lambda item: not item.nodeid.endswith(".ipynb"))  # the notebooks: longest
    moved = {id(item) for item in first}
    items[:] = first + [item for item in items if id(item) not in moved]


@pytest.fixture
def unoptimised_kernels(monkeypatch):
    """Inductor's C++ kernels at -O0 (its debug-compile switch) in a compile test: the test checks
    a compiled graph's numbers, not gcc's optimisations, and -O0 compiles a step graph about
    15 s (a fifth) faster on 2 cores. Only where little runs compiled: -O0 kernels run slowly."""
    monkeypatch.setenv("TORCHINDUCTOR_DEBUG_COMPILE", "1")
