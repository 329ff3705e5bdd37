"""Edge indices that carry their aggregation table, for message passing with static shapes.

A rollout keeps its graph (mesh, down and up edges) for every step, and a fixed-size contact
table keeps its shape. For such edges a :class:`SlottedEdgeIndex` carries, next to the edge
index, the table of every target's incoming edges (:func:`incoming_slots`): the layers then
aggregate by a dense reduction over the slots instead of a scatter (the same result up to
summation order), which is what a compiled CPU step spends most of its network time on
otherwise. The table travels with the edges, as PyG's ``EdgeIndex`` carries its metadata:
every layer and :class:`~torch_ampn.nn.AMPN` accept either a plain ``LongTensor[2, E]`` or a
:class:`SlottedEdgeIndex` wherever an edge index goes.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


def incoming_slots(edge_index: Tensor, num_nodes: int, mask: Tensor | None = None) -> Tensor:
    """Table of the incoming edges of every target node.

    Built once per graph (eager, data-dependent width); an aggregation over it has static
    shapes and needs no scatter.

    Args:
        edge_index: ``LongTensor[2, E]``, rows ``(source, target)``.
        num_nodes: Number of target nodes ``N``.
        mask: Optional ``BoolTensor[E]``: edges to leave out.

    Returns:
        ``LongTensor[N, D]`` edge ids (by increasing id), ``-1`` in unused slots; ``D`` is
        the largest in-degree (at least 1).
    """
    target = edge_index[1]
    ids = torch.arange(target.numel(), device=target.device)
    if mask is not None:
        target, ids = target[mask], ids[mask]
    order = torch.argsort(target * max(int(edge_index.size(1)), 1) + ids)  # by target, then id
    target, ids = target[order], ids[order]
    degree = torch.bincount(target, minlength=num_nodes)
    width = max(int(degree.max()) if degree.numel() else 0, 1)
    rank = torch.arange(target.numel(), device=target.device) - (torch.cumsum(degree, 0) - degree)[target]
    slots = torch.full((num_nodes, width), -1, dtype=torch.long, device=target.device)
    slots[target, rank] = ids
    return slots


class SlottedEdgeIndex(NamedTuple):
    """An edge index ``[2, E]`` with the table of every target's incoming edges ``[N_t, D]``.

    ``slots[i]`` lists the ids of the edges into target ``i`` (``-1``: unused slot); edges
    in no slot (e.g. masked slots of a contact table) are left out of the aggregation.
    Build one with :meth:`build`, or pass a table that is known by construction (a
    fixed-size contact table's slots are its edges in row-major order).
    """

    edge_index: Tensor
    slots: Tensor

    @classmethod
    def build(cls, edge_index: Tensor, num_nodes: int, mask: Tensor | None = None) -> SlottedEdgeIndex:
        """The edges ``edge_index`` into ``num_nodes`` targets with their :func:`incoming_slots` table."""
        return cls(edge_index, incoming_slots(edge_index, num_nodes, mask))


#: What the layers take as an edge index: plain, or with its aggregation table.
Edges = Tensor | SlottedEdgeIndex


def split_edges(edges: Edges) -> tuple[Tensor, Tensor | None]:
    """``(edge_index [2, E], slots [N_t, D] or None)`` of plain or slotted edges."""
    if isinstance(edges, SlottedEdgeIndex):
        return edges.edge_index, edges.slots
    return edges, None
