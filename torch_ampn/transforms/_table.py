"""Slot layout of the contact neighbour table, shared by the search backends.

Row ``i`` of the table ``[N, k * (C - 1)]`` has ``k`` slots per component other than
``component[i]``, those components in increasing id order. Query ``q = i * (C - 1) + slot``
fills the ``k`` slots of one (node, other component); unused slots hold ``i`` itself with
``mask`` False.
"""

from __future__ import annotations

import torch
from torch import Tensor


def other_slot(source_comp: Tensor, target_comp: Tensor) -> Tensor:
    """Slot of ``source_comp`` among the components other than ``target_comp`` (increasing ids)."""
    return source_comp - (source_comp > target_comp).long()


def query_component(slot: Tensor, target_comp: Tensor) -> Tensor:
    """Inverse of :func:`other_slot`: the component id of each slot."""
    return slot + (slot >= target_comp).long()


def empty_table(n: int, width: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """A table ``(nbr, mask)``, both ``[n, width]``, with no edge (every slot holds its row)."""
    nbr = torch.arange(n, device=device)[:, None].expand(n, width).contiguous()
    return nbr, torch.zeros(n, width, dtype=torch.bool, device=device)


def fill_table(nbr: Tensor, mask: Tensor, query: Tensor, index: Tensor, k: int, num_other: int) -> None:
    """Write the ``[Q, k]`` selected sources ``index`` (``-1``: none) of ``query`` into the table."""
    if query.numel() == 0:
        return
    target = torch.div(query, num_other, rounding_mode="floor")
    valid = index >= 0
    nbr.view(-1, k).index_copy_(0, query, torch.where(valid, index, target[:, None]))
    mask.view(-1, k).index_copy_(0, query, valid)
