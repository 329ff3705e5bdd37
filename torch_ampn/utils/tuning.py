"""The process-wide CPU tuning: off in a library call, on in the command-line programs and benchmarks.

Two settings change state that the whole process shares, so the package leaves them to whoever
owns the process:

* torch's thread count, which the package's loops (training, rollouts, the simulator) adapt to
  the CPU other processes leave free (:func:`torch_ampn.utils.threads.follow_free_cpu`);
* glibc's heap thresholds, raised while a compiled CPU rollout runs
  (:func:`torch_ampn.utils.heap.retained_heap`; glibc has no way to give back its adaptive
  mmap threshold afterwards).

Importing or calling the library changes neither. ``torch-ampn``, ``torch-ampn-data`` and the
scripts in ``benchmarks/`` call :func:`enable_cpu_tuning` first (their speed under load is
measured with it, benchmarks/README.md "Speed under load"); one's own program may too.
``AMPN_THREADS=off`` keeps torch's thread count alone even then, ``AMPN_THREADS=on`` follows the
free CPU without the rest.
"""

from __future__ import annotations

_enabled = False


def enable_cpu_tuning(enabled: bool = True) -> None:
    """Let the package's loops follow the free CPU and keep the heap during CPU rollouts (process-wide)."""
    global _enabled
    _enabled = bool(enabled)


def cpu_tuning_enabled() -> bool:
    """Whether :func:`enable_cpu_tuning` is in force."""
    return _enabled
