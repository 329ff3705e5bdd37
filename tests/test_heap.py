"""retained_heap: freed buffers stay in the process (no fresh page faults per step)."""

import resource
import sys

import pytest
import torch

from torch_ampn.utils.heap import heap_control_available, retained_heap

glibc = pytest.mark.skipif(
    not sys.platform.startswith("linux") or not heap_control_available(), reason="needs glibc's mallopt"
)


def _faults_of_repeated_steps(steps: int = 6, buffers: int = 24, size_mb: int = 1) -> list[int]:
    """Minor page faults of each of ``steps`` rounds that allocate, touch and free ``buffers`` buffers."""
    counts = []
    n = size_mb * 2**20 // 4
    for _ in range(steps):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        held = [torch.empty(n).fill_(1.0) for _ in range(buffers)]  # touched: every page mapped
        del held
        counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    return counts


@glibc
def test_retained_heap_reuses_the_pages_of_the_previous_step():
    pages_per_step = 24 * 2**20 // resource.getpagesize()
    with retained_heap() as active:
        assert active
        counts = _faults_of_repeated_steps()
    # the first rounds map their pages (unless the heap has room left by earlier work); from
    # the third on they are reused
    assert max(counts[2:]) < 0.05 * pages_per_step, counts


def test_retained_heap_can_be_switched_off():
    with retained_heap(enabled=False) as active:
        assert not active
