r"""A multilevel training loss: the squared error of the fine residual and of its restrictions.

A rollout accumulates the smooth, low-frequency part of the one-step error step after
step, while node-to-node jitter largely averages out; plain MSE over fine nodes weights
both alike and the jitter, the larger part, dominates it. Restricting the error to the
coarse levels of the AMG hierarchy (a weighted mean over each aggregate) keeps the smooth
part and averages the jitter away, so adding the coarse levels' squared errors puts more
weight on what accumulates:

.. math::
    \mathcal{L} = \mathrm{MSE}_0(\mathbf{e}) + \lambda \sum_{k=1}^{L}
        \frac{\sum_J W^k_J \, \|\mathbf{e}^k_J\|^2}{C \sum_J W^k_J}, \qquad
    \mathbf{e}^{k}_J = \frac{\sum_i |P^{k-1}_{iJ}|\, W^{k-1}_i\, \mathbf{e}^{k-1}_i}{W^k_J}, \quad
    W^k_J = \sum_i |P^{k-1}_{iJ}|\, W^{k-1}_i,

with :math:`W^0` the fine node mask (ply nodes), :math:`\mathbf{e}^0 = \mathbf{e}` the
per-node error of the normalised prediction and :math:`P^{k-1}` the prolongator from
level ``k`` to ``k - 1`` (the ``down`` edges' weights). Not in the seed paper, whose
recipe is :math:`\lambda = 0`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torch_ampn.nn.diffusion import masked_mean
from torch_ampn.nn.transfer import restrict_mean


def multilevel_mse(
    error: Tensor,
    node_mask: Tensor | None,
    down: Sequence[tuple[Tensor, Tensor, int]],
    coarse_weight: float = 1.0,
) -> Tensor:
    r"""The loss of the module docstring for a per-node error ``[N_0, C]``.

    Args:
        error: Per-node error of the fine level ``[N_0, C]``.
        node_mask: ``BoolTensor[N_0]`` nodes in the loss (ply nodes); all if ``None``.
        down: Per coarse level ``k = 1 .. L``: ``(down edge index [2, E], edge weight [E], N_k)``
            of the edges from level ``k - 1`` to level ``k``.
        coarse_weight: :math:`\lambda`; 0 gives the plain masked MSE.

    Returns:
        Scalar loss.
    """
    loss = masked_mean(error.square(), node_mask)
    if coarse_weight == 0:
        return loss
    weight = error.new_ones(error.size(0)) if node_mask is None else node_mask.to(error.dtype)  # [N_0]
    channels = error.size(-1)
    values = error
    for index, edge_weight, num_coarse in down:
        values, weight = restrict_mean(values, weight, index, edge_weight, num_coarse)  # [N_k, C], [N_k]
        level = (values.square() * weight.unsqueeze(-1)).sum() / (weight.sum() * channels).clamp(
            min=torch.finfo(error.dtype).tiny
        )
        loss = loss + coarse_weight * level
    return loss
