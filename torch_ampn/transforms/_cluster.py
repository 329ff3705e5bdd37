"""The ``"torch_cluster"`` backend of the contact-edge search (optional dependency).

Candidate pairs come from ``torch_cluster.radius``, which returns all neighbours of every
component; the per-component selection follows with
:func:`~torch_ampn.transforms._select.segment_topk`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_ampn.transforms._grid import squared_distance
from torch_ampn.transforms._select import segment_topk
from torch_ampn.transforms._table import empty_table, fill_table, other_slot


def torch_cluster_available() -> bool:
    """Whether the optional ``torch_cluster`` package can be imported."""
    try:
        import torch_cluster  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


def cluster_pairs(pos: Tensor, r: float, batch: Tensor) -> tuple[Tensor, Tensor]:
    """All (source, target) pairs within ``r`` (self-pairs included) from ``torch_cluster.radius``.

    ``max_num_neighbors`` grows until no node hits it, so nothing is truncated. The search
    radius is padded slightly; callers filter with the exact float64 test.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        r: Search radius.
        batch: ``[N]`` long graph id of every node.

    Returns:
        ``(source, target)``, both ``[P]``.
    """
    import torch_cluster

    n = pos.size(0)
    x = pos if pos.dtype in (torch.float32, torch.float64) else pos.float()
    order = None
    if n > 1 and bool((batch[1:] < batch[:-1]).any()):  # torch_cluster needs a sorted batch
        order = torch.argsort(batch, stable=True)
        x, batch = x[order], batch[order]
    limit = 64
    while True:
        limit = min(limit, n)
        pairs = torch_cluster.radius(x, x, r * (1 + 1e-5), batch, batch, max_num_neighbors=limit)
        if limit >= n or int(torch.bincount(pairs[0], minlength=n).max()) < limit:
            break
        limit *= 4
    target, source = pairs[0], pairs[1]
    if order is not None:
        target, source = order[target], order[source]
    return source, target


def cluster_table(
    pos: Tensor, comp: Tensor, batch: Tensor, r: float, k: int, num_comp: int
) -> tuple[Tensor, Tensor]:
    """The contact table ``(nbr, mask)``, both ``[N, k * (C - 1)]``, from :func:`cluster_pairs`.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        comp: ``[N]`` long component id of every node.
        batch: ``[N]`` long graph id of every node.
        r: Search radius.
        k: Neighbours per other component.
        num_comp: Number of components ``C``.
    """
    n, num_other = pos.size(0), num_comp - 1
    nbr, mask = empty_table(n, k * num_other, pos.device)
    if n == 0 or num_other == 0:
        return nbr, mask
    source, target = cluster_pairs(pos, r, batch)
    d2 = squared_distance(pos.to(torch.float64), source, target)
    keep = (comp[source] != comp[target]) & (d2 <= r * r)
    source, target, d2 = source[keep], target[keep], d2[keep]
    segment = target * num_other + other_slot(comp[source], comp[target])
    idx, _ = segment_topk(segment, d2, source, n * num_other, k)
    fill_table(nbr, mask, torch.arange(n * num_other, device=pos.device), idx, k, num_other)
    return nbr, mask
