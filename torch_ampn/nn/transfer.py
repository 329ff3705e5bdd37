"""Multigrid transfers between hierarchy levels with the prolongator's weights."""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.utils import scatter


def weighted_mean(edge_index: Tensor, edge_attr: Tensor, edge_weight: Tensor, num_targets: int) -> Tensor:
    r"""``\sum_j w_{ij} e_{ij} / \sum_j w_{ij}`` at every target ``i``: ``[N_t, d]``.

    Targets without incoming edges (or with weights summing to 0) get zeros.

    Args:
        edge_index: ``[2, E]``, rows ``(source j, target i)``.
        edge_attr: ``[E, d]``.
        edge_weight: ``[E]``.
        num_targets: ``N_t``.
    """
    w = edge_weight.to(edge_attr.dtype).unsqueeze(-1)  # [E, 1]
    target = edge_index[1]
    total = scatter(w * edge_attr, target, 0, dim_size=num_targets, reduce="sum")  # [N_t, d]
    norm = scatter(w, target, 0, dim_size=num_targets, reduce="sum")  # [N_t, 1]
    return torch.where(norm != 0, total / torch.where(norm != 0, norm, 1.0), 0.0)


def restrict_mean(
    values: Tensor, weight: Tensor, down_index: Tensor, down_weight: Tensor, num_coarse: int
) -> tuple[Tensor, Tensor]:
    r"""Weighted mean of fine values over each coarse node's aggregate.

    Args:
        values: Fine values ``[N_f, C]``.
        weight: Fine weights ``[N_f]`` (e.g. a 0/1 mask), non-negative.
        down_index: ``("lk", "down", "lk+1")`` edges ``[2, E]``, rows ``(fine i, coarse J)``.
        down_weight: Prolongator values :math:`P_{iJ}` of those edges ``[E]`` (their magnitude is used).
        num_coarse: Number of coarse nodes ``N_c``.

    Returns:
        ``(mean [N_c, C], coarse weight [N_c])``; a coarse node with zero weight has mean 0.
    """
    fine, coarse = down_index
    w = down_weight.abs().to(values.dtype) * weight.to(values.dtype)[fine]  # [E]
    total = values.new_zeros(num_coarse).index_add_(0, coarse, w)  # [N_c]
    summed = values.new_zeros(num_coarse, values.size(-1)).index_add_(
        0, coarse, w.unsqueeze(-1) * values[fine]
    )  # [N_c, C]
    mean = summed / total.clamp(min=torch.finfo(values.dtype).tiny).unsqueeze(-1)
    return mean, total
