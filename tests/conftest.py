"""Fixtures shared by several test files (pure helpers live in ``torch_ampn.testing``).

Imports are inside the fixtures, so that collecting a test file that uses none stays cheap.
"""

import os

import pytest

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
def small_runs(small_sim):
    """Seeds 3 and 4 of ``small_sim``, simulated once per session: read them, never modify them."""
    from torch_ampn.sim import simulate_batch

    return simulate_batch(small_sim, seeds=[3, 4])
