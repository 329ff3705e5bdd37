"""Inter-level message passing: eq. (2) of the seed paper (down- and up-sampling edges)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch_geometric.nn.conv import MessagePassing

from torch_ampn.nn.intra_level_conv import check_aggr
from torch_ampn.nn.mlp import MLP


class InterLevelConv(MessagePassing):
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

    with bias-free linear maps :math:`\mathbf{W}` and :class:`~torch_ampn.nn.MLP` s :math:`f`.
    ``edge_index`` rows are ``(source j, target i)``: for down-sampling the sources are the
    fine level-:math:`l` nodes and the targets the level-:math:`l+1` nodes, for up-sampling
    the reverse. Sender embeddings are not changed. Receivers without incoming edges
    aggregate to zeros.

    Args:
        channels: Size :math:`d` of node and edge embeddings.
        hidden_channels: Hidden width of the MLPs (paper: 128).
        aggr: The aggregation :math:`\bigoplus`: ``"max"``, ``"sum"`` or ``"mean"``.
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.

    Shapes:
        - **input:**
          node embeddings :math:`((|\mathcal{V}_s|, d), (|\mathcal{V}_t|, d))`,
          edge indices :math:`(2, |\mathcal{E}|)`, edge embeddings :math:`(|\mathcal{E}|, d)`
        - **output:** receiver embeddings :math:`(|\mathcal{V}_t|, d)`, edge embeddings
          :math:`(|\mathcal{E}|, d)`
    """

    def __init__(self, channels: int, hidden_channels: int = 128, aggr: str = "max", **kwargs) -> None:
        super().__init__(aggr=check_aggr(aggr), **kwargs)
        self.channels = channels
        self.hidden_channels = hidden_channels
        self.lin_edge = nn.Linear(channels, channels, bias=False)
        self.mlp_edge = MLP(3 * channels, channels, hidden_channels)
        self.lin_node = nn.Linear(channels, channels, bias=False)
        self.mlp_node = MLP(2 * channels, channels, hidden_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Reset all learnable parameters."""
        super().reset_parameters()
        for module in (self.lin_edge, self.mlp_edge, self.lin_node, self.mlp_node):
            module.reset_parameters()

    def forward(
        self, x: tuple[Tensor, Tensor], edge_index: Tensor, edge_attr: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Run one layer of eq. (2).

        Args:
            x: ``(x_src [N_s, d], x_dst [N_t, d])``: sender and receiver embeddings.
            edge_index: ``[2, E]``, rows ``(source j in x_src, target i in x_dst)``.
            edge_attr: Edge embeddings ``[E, d]``.

        Returns:
            ``(x_dst, edge_attr)``: new receiver embeddings ``[N_t, d]`` and edge embeddings ``[E, d]``.
        """
        x_src, x_dst = x
        size = (x_src.size(0), x_dst.size(0))
        edge_attr = self.lin_edge(edge_attr) + self.mlp_edge.forward_edges(
            x_dst, x_src, edge_attr, edge_index
        )  # [E, d]
        agg = self.propagate(edge_index, edge_attr=edge_attr, size=size)  # [N_t, d]
        x_dst = self.lin_node(x_dst) + self.mlp_node(torch.cat([x_dst, agg], dim=-1))  # [N_t, d]
        return x_dst, edge_attr

    def message(self, edge_attr: Tensor) -> Tensor:
        """The message of edge ``(j, i)`` is its updated embedding: ``[E, d]``."""
        return edge_attr

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.channels}, hidden_channels={self.hidden_channels}, "
            f"aggr={self.aggr!r})"
        )
