"""Per-segment k smallest of candidate pairs, ordered by (distance, node index)."""

from __future__ import annotations

import torch
from torch import Tensor

_NONE = torch.iinfo(torch.long).max


def segment_topk(
    segment: Tensor, dist2: Tensor, source: Tensor, num_segments: int, k: int
) -> tuple[Tensor, Tensor]:
    """The ``k`` nearest sources of every segment, ties broken by the smaller source index.

    Runs ``k`` selection rounds, each two segment-wise minimum reductions (distance, then
    index among the pairs at that distance): exact, deterministic, no sort, no ``N x N``.
    Every (segment, source) pair must occur at most once.

    Args:
        segment: ``[P]`` segment of each pair (``0 .. num_segments - 1``).
        dist2: ``[P]`` float squared distance of each pair.
        source: ``[P]`` long source node of each pair.
        num_segments: Number of segments ``S``.
        k: Number of sources kept per segment.

    Returns:
        ``(index, dist2)``, both ``[S, k]``, nearest first: ``index`` holds the chosen source
        or ``-1`` where the segment has fewer than ``k`` pairs; ``dist2`` their squared
        distances (``inf`` where ``index`` is ``-1``).
    """
    device = dist2.device
    index = torch.full((num_segments, k), -1, dtype=torch.long, device=device)
    best_d2 = torch.full((num_segments, k), float("inf"), dtype=dist2.dtype, device=device)
    if dist2.numel() == 0:
        return index, best_d2
    alive = dist2.clone()
    for t in range(k):
        best = torch.full((num_segments,), float("inf"), dtype=dist2.dtype, device=device)
        best.scatter_reduce_(0, segment, alive, "amin")
        at_best = (alive == best.index_select(0, segment)) & (alive < float("inf"))
        first = torch.full((num_segments,), _NONE, dtype=torch.long, device=device)
        first.scatter_reduce_(0, segment, torch.where(at_best, source, _NONE), "amin")
        chosen = at_best & (source == first.index_select(0, segment))
        index[:, t] = torch.where(first == _NONE, -1, first)
        best_d2[:, t] = best
        alive.masked_fill_(chosen, float("inf"))
    return index, best_d2
