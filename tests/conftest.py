"""Fixtures shared by several test files (pure helpers live in ``torch_ampn.testing``).

Imports are inside the fixtures, so that collecting a test file that uses none stays cheap.
"""

import pytest


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
