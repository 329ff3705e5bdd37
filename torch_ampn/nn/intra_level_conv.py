"""Intra-level message passing: eq. (1) of the seed paper (mesh and contact edges of one level)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.typing import OptTensor

from torch_ampn.nn.mlp import MLP

AGGREGATIONS = ("max", "sum", "mean")


def check_aggr(aggr: str) -> str:
    """Return ``aggr`` if it is one of :data:`AGGREGATIONS`, else raise ``ValueError``."""
    if aggr not in AGGREGATIONS:
        raise ValueError(f"aggr must be one of {AGGREGATIONS}, got {aggr!r}")
    return aggr


class IntraLevelConv(MessagePassing):
    r"""The intra-level message passing layer of AMPNs (seed paper, eq. (1)).

    Contact edges :math:`\mathcal{E}^C` and mesh edges :math:`\mathcal{E}^M` of one hierarchy
    level are updated first, from the old node embeddings; the nodes are then updated from
    the aggregated *new* edge embeddings:

    .. math::
        \mathbf{e}^{C\prime}_{ij} &= \mathbf{W}_{C}\, \mathbf{e}^{C}_{ij}
            + f_{C}\left(\mathbf{k}_i, \mathbf{k}_j, \mathbf{e}^{C}_{ij}\right)

        \mathbf{e}^{M\prime}_{ij} &= \mathbf{W}_{M}\, \mathbf{e}^{M}_{ij}
            + f_{M}\left(\mathbf{k}_i, \mathbf{k}_j, \mathbf{e}^{M}_{ij}\right)

        \mathbf{k}^{\prime}_i &= \mathbf{W}_{V}\, \mathbf{k}_i
            + f_{V}\left(\mathbf{k}_i, \bigoplus_{j \in \mathcal{N}^C(i)} \mathbf{e}^{C\prime}_{ij},
            \bigoplus_{j \in \mathcal{N}^M(i)} \mathbf{e}^{M\prime}_{ij}\right)

    where the :math:`\mathbf{W}` are bias-free linear maps (residual weight matrices), the
    :math:`f` are :class:`~torch_ampn.nn.MLP` s (``LayerNorm -> Linear -> SiLU -> Linear``) of
    the concatenated arguments, :math:`i` is the edge's target and :math:`j` its source
    (``edge_index`` rows ``(j, i)``, PyG's ``source_to_target`` flow), and :math:`\bigoplus`
    is a max (default), sum or mean over the incoming edges; a node without incoming edges
    aggregates to zeros.

    Args:
        channels: Size :math:`d` of node and edge embeddings.
        hidden_channels: Hidden width of the MLPs (paper: 128).
        aggr: The aggregation :math:`\bigoplus`: ``"max"``, ``"sum"`` or ``"mean"``.
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.

    Shapes:
        - **input:**
          node embeddings :math:`(|\mathcal{V}|, d)`,
          mesh edge indices :math:`(2, |\mathcal{E}^M|)`, mesh edge embeddings
          :math:`(|\mathcal{E}^M|, d)`,
          contact edge indices :math:`(2, |\mathcal{E}^C|)`, contact edge embeddings
          :math:`(|\mathcal{E}^C|, d)`, contact mask :math:`(|\mathcal{E}^C|)` *(optional)*
        - **output:** node embeddings :math:`(|\mathcal{V}|, d)`, mesh edge embeddings
          :math:`(|\mathcal{E}^M|, d)`, contact edge embeddings :math:`(|\mathcal{E}^C|, d)`
    """

    def __init__(self, channels: int, hidden_channels: int = 128, aggr: str = "max", **kwargs) -> None:
        super().__init__(aggr=check_aggr(aggr), **kwargs)
        self.channels = channels
        self.hidden_channels = hidden_channels
        self.lin_contact = nn.Linear(channels, channels, bias=False)
        self.mlp_contact = MLP(3 * channels, channels, hidden_channels)
        self.lin_mesh = nn.Linear(channels, channels, bias=False)
        self.mlp_mesh = MLP(3 * channels, channels, hidden_channels)
        self.lin_node = nn.Linear(channels, channels, bias=False)
        self.mlp_node = MLP(3 * channels, channels, hidden_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Reset all learnable parameters."""
        super().reset_parameters()
        for module in (
            self.lin_contact,
            self.mlp_contact,
            self.lin_mesh,
            self.mlp_mesh,
            self.lin_node,
            self.mlp_node,
        ):
            module.reset_parameters()

    def forward(
        self,
        x: Tensor,
        mesh_index: Tensor,
        e_mesh: Tensor,
        contact_index: Tensor,
        e_contact: Tensor,
        contact_mask: OptTensor = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Run one layer of eq. (1).

        Args:
            x: Node embeddings ``[N, d]``.
            mesh_index: Mesh edges ``[2, E]``, rows ``(source j, target i)``.
            e_mesh: Mesh edge embeddings ``[E, d]``.
            contact_index: Contact edges ``[2, M]``, rows ``(source j, target i)``.
            e_contact: Contact edge embeddings ``[M, d]``.
            contact_mask: Optional ``BoolTensor[M]``: ``False`` marks an unused slot of a
                fixed-size contact table. Such edges do not contribute to the aggregation
                (exactly as if they were removed) and their output embeddings are zero;
                their indices must still be valid node indices (e.g. the node itself).

        Returns:
            ``(x, e_mesh, e_contact)`` with the shapes of the inputs.
        """
        num_nodes = x.size(0)
        e_contact = self.lin_contact(e_contact) + self.mlp_contact.forward_edges(
            x, x, e_contact, contact_index
        )  # [M, d]
        e_mesh = self.lin_mesh(e_mesh) + self.mlp_mesh.forward_edges(x, x, e_mesh, mesh_index)  # [E, d]

        agg_mesh = self.propagate(mesh_index, edge_attr=e_mesh, size=(num_nodes, num_nodes))  # [N, d]
        if contact_mask is None:
            agg_contact = self.propagate(contact_index, edge_attr=e_contact, size=(num_nodes, num_nodes))
        else:
            # Send masked-out messages to a dummy node N, dropped afterwards: exact for
            # every aggregation (max, sum, mean) and free of data-dependent shapes.
            target = torch.where(contact_mask, contact_index[1], num_nodes)  # [M]
            index = torch.stack([contact_index[0], target])  # [2, M]
            agg_contact = self.propagate(index, edge_attr=e_contact, size=(num_nodes, num_nodes + 1))
            agg_contact = agg_contact[:num_nodes]  # [N, d]
            e_contact = torch.where(contact_mask.unsqueeze(-1), e_contact, 0.0)

        x = self.lin_node(x) + self.mlp_node(torch.cat([x, agg_contact, agg_mesh], dim=-1))  # [N, d]
        return x, e_mesh, e_contact

    def message(self, edge_attr: Tensor) -> Tensor:
        """The message of edge ``(j, i)`` is its updated embedding: ``[E, d]``."""
        return edge_attr

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.channels}, hidden_channels={self.hidden_channels}, "
            f"aggr={self.aggr!r})"
        )
