"""Inter-level message passing: eq. (2) of the seed paper (down- and up-sampling edges)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.nn.aggr import Aggregation
from torch_geometric.typing import OptTensor

from torch_ampn.nn._conv import EmbeddingConv
from torch_ampn.nn.slots import Edges, split_edges
from torch_ampn.nn.transfer import weighted_mean


class InterLevelConv(EmbeddingConv):
    r"""The inter-level (up/down-sampling) message passing layer of AMPNs (seed paper, eq. (2)).

    A bipartite layer from sender nodes :math:`\mathcal{V}^{send}` to receiver nodes
    :math:`\mathcal{V}^{rec}` on another hierarchy level. Edge embeddings are updated from
    the receiver and sender embeddings, then the receivers from the aggregated new edges:

    .. math::
        \mathbf{e}^{\prime}_{ij} &= \mathbf{W}_{E}\, \mathbf{e}_{ij}
            + f_{E}\left(\mathbf{k}^{rec}_i, \mathbf{k}^{send}_j, \mathbf{e}_{ij}\right)

        \mathbf{k}^{rec\prime}_i &= \mathbf{W}_{V}\, \mathbf{k}^{rec}_i
            + f_{V}\left(\mathbf{k}^{rec}_i, \bigoplus_{j \in \mathcal{N}(i)}
            \mathbf{e}^{\prime}_{ij}\right)

    with bias-free linear maps :math:`\mathbf{W}` and :class:`~torch_ampn.nn.LayerNormMLP` s :math:`f`.
    ``edge_index`` rows are ``(source j, target i)``: for down-sampling the sources are the
    fine level-:math:`l` nodes and the targets the level-:math:`l+1` nodes, for up-sampling
    the reverse. Sender embeddings are not changed. Receivers without incoming edges
    aggregate to zeros.

    Args:
        channels: Size :math:`d` of node and edge embeddings.
        mlp_channels: Hidden width of the MLPs (paper: 128).
        aggr: The aggregation :math:`\bigoplus`: ``"max"``, ``"sum"``, ``"mean"`` or a
            ``torch_geometric.nn.aggr.Aggregation``.
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.

    Shapes:
        - **input:**
          node embeddings :math:`((|\mathcal{V}_s|, d), (|\mathcal{V}_t|, d))`,
          edge indices :math:`(2, |\mathcal{E}|)`, edge embeddings :math:`(|\mathcal{E}|, d)`
        - **output:** receiver embeddings :math:`(|\mathcal{V}_t|, d)`, edge embeddings
          :math:`(|\mathcal{E}|, d)`
    """

    def __init__(
        self, channels: int, mlp_channels: int = 128, aggr: str | Aggregation = "max", **kwargs
    ) -> None:
        super().__init__(channels, mlp_channels, aggr, **kwargs)
        self.lin_edge, self.mlp_edge = self.residual(), self.mlp(3)
        self.lin_node, self.mlp_node = self.residual(), self.mlp(2)
        self.reset_parameters()

    def forward(
        self, x: tuple[Tensor, Tensor], edge_index: Edges, edge_attr: Tensor, edge_weight: OptTensor = None
    ) -> tuple[Tensor, Tensor]:
        r"""Run one layer of eq. (2).

        Args:
            x: ``(x_src [N_s, d], x_dst [N_t, d])``: sender and receiver embeddings.
            edge_index: ``[2, E]``, rows ``(source j in x_src, target i in x_dst)``; a
                :class:`~torch_ampn.nn.SlottedEdgeIndex` aggregates by a dense reduction over
                its table (same result).
            edge_attr: Edge embeddings ``[E, d]``.
            edge_weight: Optional ``[E]`` weights :math:`w_{ij}`: the aggregation is then the
                weighted mean :math:`\sum_j w_{ij} \mathbf{e}^{\prime}_{ij} / \sum_j w_{ij}`
                (instead of ``aggr``), the multigrid transfer with the prolongator's weights
                (``edge_weight`` of :func:`~torch_ampn.hierarchy.build_hierarchy`'s down and up
                edges): interpolation on up edges (each row of :math:`P` sums to 1), the
                normalised restriction :math:`P^\top` on down edges. Plain ``edge_index`` only.

        Returns:
            ``(x_dst, edge_attr)``: new receiver embeddings ``[N_t, d]`` and edge embeddings ``[E, d]``.
        """
        x_src, x_dst = x
        size = (x_src.size(0), x_dst.size(0))
        edge_attr = self.mlp_edge.forward_edges(
            x_dst, x_src, edge_attr, split_edges(edge_index)[0], self.lin_edge.weight
        )  # [E, d]: W e + f(k_i, k_j, e)
        if edge_weight is None:
            agg = self.aggregate_edges(edge_index, edge_attr, size)  # [N_t, d]
        else:
            agg = weighted_mean(split_edges(edge_index)[0], edge_attr, edge_weight, size[1])  # [N_t, d]
        x_dst = self.lin_node(x_dst) + self.mlp_node(torch.cat([x_dst, agg], dim=-1))  # [N_t, d]
        return x_dst, edge_attr
