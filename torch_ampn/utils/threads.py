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
On an otherwise idle machine ``OMP_WAIT_POLICY=ACTIVE`` is up to 1.3x faster; ``AMPN_THREADS=off``
leaves torch as it comes.
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

#: The wait policy set unless the user chose one.
WAIT_POLICY = "PASSIVE"
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
