"""Relative-position edge features (the seed paper's), for any edge set of a hierarchy."""

from __future__ import annotations

import torch
from torch import Tensor


def edge_features(
    edge_index: Tensor,
    pos_src: Tensor,
    pos_dst: Tensor,
    pos0_src: Tensor | None = None,
    pos0_dst: Tensor | None = None,
) -> Tensor:
    """Relative-position features of edges ``(source j, target i)``.

    Args:
        edge_index: ``LongTensor[2, E]``, rows ``(source j, target i)``.
        pos_src: Current positions of the source node set ``[N_s, 3]``.
        pos_dst: Current positions of the target node set ``[N_t, 3]`` (the same tensor
            as ``pos_src`` for edges within one level).
        pos0_src: Initial positions of the sources ``[N_s, 3]``, or ``None``.
        pos0_dst: Initial positions of the targets ``[N_t, 3]``, or ``None``.

    Returns:
        ``[E, 4]`` = ``[x_i - x_j, |x_i - x_j|]``, or ``[E, 8]`` with
        ``[x0_i - x0_j, |x0_i - x0_j|]`` appended when initial positions are given.
    """
    src, dst = edge_index[0], edge_index[1]
    rel = pos_dst[dst] - pos_src[src]  # [E, 3]
    parts = [rel, rel.norm(dim=-1, keepdim=True)]
    if pos0_src is not None and pos0_dst is not None:
        rel0 = pos0_dst[dst] - pos0_src[src]  # [E, 3]
        parts += [rel0, rel0.norm(dim=-1, keepdim=True)]
    return torch.cat(parts, dim=-1)
