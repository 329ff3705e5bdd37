"""How torch's OpenMP threads wait, chosen before torch starts its thread pool.

torch's CPU kernels run on an OpenMP pool (GNU libgomp in the Linux wheels) whose idle
threads spin before they sleep. On a machine whose cores other processes share, a thread
that spins at a barrier burns the core its partner needs, and a job runs tens of times
slower: a quickstart training step 68x, a fast rollout and a simulated trajectory more than
40x beside one busy process (benchmarks/README.md, "Speed under load").
:func:`configure_threads` makes them sleep instead (``OMP_WAIT_POLICY=PASSIVE``) unless the
user chose a wait policy or a spin count, before torch is imported: ``import torch_ampn``
calls it, so the ``torch-ampn`` commands, the data generator and the benchmarks get it.
Import ``torch_ampn`` before ``torch`` (or set the variable yourself) in your own scripts.

Sleeping threads cost a wake-up per parallel region, which latency-bound work pays hundreds of
times per step: a rollout step and a simulator sub-step are many small kernels. Those run on
:data:`LATENCY_BOUND_THREADS` intra-op thread (:func:`latency_bound_threads`), which waits for
no other thread at all; training, whose large products use both cores, keeps torch's count.
``AMPN_THREADS=off`` leaves torch as it comes (its wait policy and thread count everywhere).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator, MutableMapping
from contextlib import contextmanager
from typing import Any

#: The wait policy set unless the user chose one.
WAIT_POLICY = "PASSIVE"
#: Intra-op threads of latency-bound CPU work (a rollout, the simulator): see :func:`latency_bound_threads`.
LATENCY_BOUND_THREADS = 1
#: Largest work per kernel (elements, e.g. settings x nodes x channels) counted as latency-bound,
#: the bound below which the fast rollout also writes its wrapper in C++. Measured latency-bound:
#: the quickstart network on the coarse mesh, one setting at a time (1,670 x 32 = 53,440); larger
#: work (a batch of 8 such settings, 427,520; the paper's network on its mesh) keeps torch's
#: thread count, where more threads may pay (not measured).
LATENCY_BOUND_ELEMENTS = 1 << 18
#: Settings that, when the user set them, win over :data:`WAIT_POLICY`.
USER_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def configure_threads(environ: MutableMapping[str, str] | None = None) -> str:
    """Set ``OMP_WAIT_POLICY`` in ``environ`` (default ``os.environ``) unless told not to.

    Returns what was done: ``"off"`` (``AMPN_THREADS=off``), ``"user"`` (a wait policy or
    spin count is already set), ``"late"`` (torch is already imported: its pool has read its
    settings, nothing is changed) or ``"wait=PASSIVE"``.
    """
    environ = os.environ if environ is None else environ
    if environ.get("AMPN_THREADS", "").lower() == "off":
        return "off"
    if any(k in environ for k in USER_SETTINGS):
        return "user"
    if "torch" in sys.modules:
        return "late"
    environ["OMP_WAIT_POLICY"] = WAIT_POLICY
    return f"wait={WAIT_POLICY}"


@contextmanager
def latency_bound_threads(device: Any = None, elements: int | None = None) -> Iterator[None]:
    """Run the block on :data:`LATENCY_BOUND_THREADS` intra-op thread(s), then restore torch's count.

    For work made of many small kernels on the CPU (a rollout, the simulator): one thread
    runs them without waking or waiting for another, which on 2 cores is faster than two
    sleeping threads and, unlike two spinning ones, keeps its speed beside other busy
    processes (benchmarks/README.md, "Speed under load"). Compiled code built inside the
    block is built for that thread count. Nothing changes for a ``device`` other than the
    CPU, for ``elements`` (the size of the work's typical kernel) above
    :data:`LATENCY_BOUND_ELEMENTS`, with ``AMPN_THREADS=off``, or where torch already uses
    no more threads.
    """
    import torch

    off = os.environ.get("AMPN_THREADS", "").lower() == "off"
    cpu = device is None or torch.device(device).type == "cpu"
    large = elements is not None and elements > LATENCY_BOUND_ELEMENTS
    before = torch.get_num_threads()
    if off or not cpu or large or before <= LATENCY_BOUND_THREADS:
        yield
        return
    torch.set_num_threads(LATENCY_BOUND_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)
