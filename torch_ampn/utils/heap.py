"""Keep freed memory in the process heap while a CPU rollout runs (glibc only).

A compiled CPU step allocates its intermediate buffers (``[E, d]`` edge features, about 1 MB
each on the default mesh) with ``malloc``. With glibc's adaptive thresholds every step hands
most of them back to the operating system (``munmap`` or a heap trim) and faults the pages in
again at the next step; on the 2-core development VM these page faults were about a tenth of
a fast quickstart rollout (2026-11-29, ``benchmarks/rollout.py``). :func:`retained_heap` sets
glibc's ``M_MMAP_THRESHOLD`` to its maximum (32 MiB: smaller buffers come from the heap) and
``M_TRIM_THRESHOLD`` high for the duration, so the step reuses the pages of the previous one.
On exit the trim threshold goes to 64 MiB (twice the mmap threshold, where glibc's own
adaptive rule would put it): the heap shrinks again at the next ``free``. Elsewhere (macOS,
musl, Windows) it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
from collections.abc import Iterator

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: The largest mmap threshold glibc accepts on 64-bit systems (its ``DEFAULT_MMAP_THRESHOLD_MAX``).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Trim threshold inside :func:`retained_heap` (``mallopt`` takes an ``int``).
RETAINED_TRIM = 2**31 - 1
#: Trim threshold after it: twice the mmap threshold, glibc's adaptive rule.
TRIM_AFTER = 2 * MMAP_THRESHOLD


@functools.cache
def _mallopt():
    """The C library's ``mallopt`` (glibc), or ``None`` where it has none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallopt
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return fn


def heap_control_available() -> bool:
    """Whether :func:`retained_heap` can change the allocator (a C library with ``mallopt``)."""
    return _mallopt() is not None


@contextlib.contextmanager
def retained_heap(enabled: bool = True) -> Iterator[bool]:
    """Keep freed memory in the heap inside the ``with`` block; yields whether it could.

    Not thread-aware: the setting is process-wide. Nesting is harmless (the innermost exit
    lowers the trim threshold early, which only costs speed).
    """
    mallopt = _mallopt() if enabled else None
    if mallopt is None:
        yield False
        return
    ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, RETAINED_TRIM))
    try:
        yield ok
    finally:
        mallopt(M_TRIM_THRESHOLD, TRIM_AFTER)
