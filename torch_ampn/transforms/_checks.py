"""Argument checks of the contact-edge search (:mod:`torch_ampn.transforms.radius`).

Every check raises ``ValueError`` with a message naming the argument.
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from torch_ampn.transforms._cluster import torch_cluster_available
from torch_ampn.transforms._native import native_available

BACKENDS = ("auto", "grid", "native", "torch_cluster")


def check_positions(pos: Tensor) -> None:
    """Check that ``pos`` is a finite floating point ``[N, 3]`` tensor."""
    if not isinstance(pos, Tensor):
        raise ValueError(f"pos must be a torch.Tensor, got {type(pos).__name__}")
    if pos.dim() != 2 or pos.size(1) != 3:
        raise ValueError(f"pos must have shape [N, 3], got {list(pos.shape)}")
    if not pos.is_floating_point():
        raise ValueError(f"pos must be a floating point tensor, got dtype {pos.dtype}")
    if pos.numel() and not bool(torch.isfinite(pos).all()):
        raise ValueError("pos contains NaN or infinite values")


def check_radius(r: float) -> float:
    """The search radius ``r`` as a float, checked positive and finite."""
    if isinstance(r, bool) or not isinstance(r, numbers.Real):
        raise ValueError(f"r must be a number, got {type(r).__name__}")
    if not math.isfinite(r) or r <= 0:
        raise ValueError(f"r must be positive and finite, got {r}")
    return float(r)


def check_count(value: int, name: str) -> int:
    """``value`` as an int, checked ``>= 1`` (``name`` labels the error)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def check_labels(labels: Tensor, num_nodes: int, name: str) -> None:
    """Check that ``labels`` is a ``[num_nodes]`` integer tensor of ids ``>= 0``."""
    if not isinstance(labels, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(labels).__name__}")
    if labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got dtype {labels.dtype}")
    if labels.dim() != 1:
        raise ValueError(f"{name} must have shape [N], got {list(labels.shape)}")
    if labels.numel() != num_nodes:
        raise ValueError(f"{name} has {labels.numel()} entries but pos has {num_nodes} nodes")
    if num_nodes and int(labels.min()) < 0:
        raise ValueError(f"{name} contains negative ids (smallest {int(labels.min())})")


def check_backend(backend: str, device: torch.device | None = None) -> str:
    """The backend that runs for ``backend``, checked available.

    ``"auto"`` is ``"native"`` for positions on the CPU (``device``) where a C compiler built
    it, else ``"grid"``; without a ``device`` (callers that have no native search) ``"grid"``.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "torch_cluster" and not torch_cluster_available():
        raise ValueError("backend='torch_cluster' needs the optional package torch-cluster")
    if backend == "native" and not native_available():
        raise ValueError("backend='native' needs a C compiler (cc or $CC) and no TORCH_AMPN_NO_COMPILE=1")
    if backend == "auto":
        on_cpu = device is not None and torch.device(device).type == "cpu"
        return "native" if on_cpu and native_available() else "grid"
    return backend


def check_cell_size(cell_size: float | None) -> None:
    """Check that ``cell_size`` is ``None`` or a positive finite number."""
    if cell_size is None:
        return
    if isinstance(cell_size, bool) or not isinstance(cell_size, numbers.Real):
        raise ValueError(f"cell_size must be a number or None, got {type(cell_size).__name__}")
    if not math.isfinite(cell_size) or cell_size <= 0:
        raise ValueError(f"cell_size must be positive and finite, got {cell_size}")


def prepare_batch(batch: Tensor | None, pos: Tensor) -> tuple[Tensor, int]:
    """Graph id of every node (zeros without ``batch``) and the number of graphs."""
    n = pos.size(0)
    if batch is None:
        return torch.zeros(n, dtype=torch.long, device=pos.device), 1
    check_labels(batch, n, "batch")
    batch = batch.to(pos.device, torch.long)
    return batch, (int(batch.max()) + 1 if n else 1)


def prepare_components(component: Tensor, pos: Tensor, num_components: int | None) -> tuple[Tensor, int]:
    """Component ids as long on ``pos``'s device and the number of components ``C``."""
    n = pos.size(0)
    check_labels(component, n, "component")
    component = component.to(pos.device, torch.long)
    largest = int(component.max()) if n else -1
    if num_components is None:
        return component, max(largest + 1, 1)
    check_count(num_components, "num_components")
    if largest >= num_components:
        raise ValueError(f"component contains id {largest} but num_components={num_components}")
    return component, num_components
