"""The ``"native"`` backend of the contact-edge search: a cell grid in C, built at first use.

The pure PyTorch grid search (:mod:`torch_ampn.transforms._grid_search`) launches a few
hundred small kernels per call, which bounds a CPU rollout on a small mesh (about 6-10 ms
per step for the coarse default mesh). ``_native.c`` does the same search in one pass of
plain C: a counting sort of the nodes into cells of edge ``>= r`` per (graph, component),
then the ``3 x 3 x 3`` cells around every node. Same float64 distances (no fused
multiply-add), same ties, same table.

The C file is compiled once with the system C compiler (``$CC``, else ``cc``) into
``$TORCH_AMPN_CACHE`` (default ``~/.cache/torch_ampn``), keyed by the source's hash, and
loaded with :mod:`ctypes`; no PyTorch headers, so a build takes well under a second. The
build is logged (``logging`` level INFO, logger ``torch_ampn.transforms._native``: the
compiler and the file). Where there is no compiler, or with ``TORCH_AMPN_NO_COMPILE=1`` (or
the older ``TORCH_AMPN_NATIVE=0``) in the environment before the first search, nothing is
compiled or loaded: :func:`native_available` is ``False`` and ``backend="auto"`` takes the
PyTorch grid (per call: ``backend="grid"``).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import torch
from torch import Tensor

SOURCE = Path(__file__).with_name("_native.c")
#: Most cells (over all groups) the C grid allocates; coarser cells keep it below.
MAX_CELLS = 1 << 22

logger = logging.getLogger(__name__)


def _cache_dir() -> Path:
    root = os.environ.get("TORCH_AMPN_CACHE") or Path.home() / ".cache" / "torch_ampn"
    return Path(root)


def _switched_off() -> bool:
    """Whether ``TORCH_AMPN_NO_COMPILE=1`` (or the older ``TORCH_AMPN_NATIVE=0``) turns the C search off."""
    off = os.environ.get("TORCH_AMPN_NO_COMPILE", "0") not in ("", "0")
    return off or os.environ.get("TORCH_AMPN_NATIVE") == "0"


@functools.cache
def _library() -> ctypes.CDLL | None:
    """The compiled search (built into the cache at the first call), or ``None`` without a compiler."""
    if _switched_off():
        return None
    source = SOURCE.read_bytes()
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        return None
    tag = hashlib.sha256(source + compiler.encode()).hexdigest()[:16]
    target = _cache_dir() / f"ampn_native_{tag}.so"
    if not target.exists():
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
                built = Path(tmp) / target.name
                flags = ["-O3", "-ffp-contract=off", "-fPIC", "-shared"]  # no FMA: the same sums
                cmd = [compiler, *flags, str(SOURCE), "-o", str(built), "-lm"]
                logger.info(
                    "compiling the C contact search with %s into %s (once; TORCH_AMPN_NO_COMPILE=1 "
                    "takes the PyTorch grid instead)",
                    compiler,
                    target,
                )
                subprocess.run(cmd, check=True, capture_output=True, timeout=120)
                os.replace(built, target)  # atomic: concurrent builders all end with one file
        except (OSError, subprocess.SubprocessError) as err:
            logger.info("the C contact search did not compile (%s): the PyTorch grid runs instead", err)
            return None
    try:
        lib = ctypes.CDLL(str(target))
    except OSError:
        return None
    fn = lib.ampn_component_table
    fn.restype = ctypes.c_int
    fn.argtypes = [
        ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
        ctypes.c_double, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p,
    ]  # fmt: skip
    return lib


def native_available() -> bool:
    """Whether the C search could be built and loaded (a C compiler is there)."""
    return _library() is not None


def native_table(
    pos: Tensor, component: Tensor, batch: Tensor, num_graphs: int, r: float, k: int, num_components: int
) -> tuple[Tensor, Tensor]:
    """:func:`~torch_ampn.transforms.component_radius_table` on the CPU by the C grid.

    Args:
        pos: ``[N, 3]`` positions (CPU).
        component: ``LongTensor[N]`` component ids in ``[0, C)``.
        batch: ``LongTensor[N]`` graph ids in ``[0, num_graphs)``.
        num_graphs: Graphs of the batch.
        r: Radius (inclusive).
        k: Neighbours per other component.
        num_components: ``C``.

    Returns:
        ``(nbr, mask)``, ``[N, k * (C - 1)]`` each.
    """
    lib = _library()
    if lib is None:
        raise RuntimeError("the native contact search needs a C compiler and no TORCH_AMPN_NO_COMPILE=1")
    if pos.device.type != "cpu":
        raise ValueError(f"backend='native' runs on the CPU, got positions on {pos.device}")
    n, c = pos.size(0), num_components
    p = pos.detach().to(torch.float64).contiguous()
    group = (batch * c + component).contiguous()
    nbr = torch.empty(n, k * (c - 1), dtype=torch.long)
    mask = torch.empty(n, k * (c - 1), dtype=torch.bool)
    status = lib.ampn_component_table(
        n, p.data_ptr(), group.data_ptr(), c, num_graphs * c, float(r), MAX_CELLS, k,
        nbr.data_ptr(), mask.data_ptr(),
    )  # fmt: skip
    if status != 0:
        raise MemoryError("the native contact search could not allocate its cell grid")
    return nbr, mask
