"""Intra-level message passing: eq. (1) of the seed paper (mesh and contact edges of one level)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.nn.aggr import Aggregation
from torch_geometric.typing import OptTensor

from torch_ampn.nn._conv import EmbeddingConv
from torch_ampn.nn.slots import Edges, split_edges


class IntraLevelConv(EmbeddingConv):
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
    :math:`f` are :class:`~torch_ampn.nn.LayerNormMLP` s (``LayerNorm -> Linear -> SiLU -> Linear``) of
    the concatenated arguments, :math:`i` is the edge's target and :math:`j` its source
    (``edge_index`` rows ``(j, i)``, PyG's ``source_to_target`` flow), and :math:`\bigoplus`
    is a max (default), sum or mean over the incoming edges; a node without incoming edges
    aggregates to zeros.

    With ``contact=False`` the layer has mesh edges only (no :math:`\mathbf{W}_C`, :math:`f_C`,
    and :math:`f_V` of :math:`\mathbf{k}_i` and the mesh aggregation): a MeshGraphNet layer.

    Args:
        channels: Size :math:`d` of node and edge embeddings.
        mlp_channels: Hidden width of the MLPs (paper: 128).
        aggr: The aggregation :math:`\bigoplus`: ``"max"``, ``"sum"``, ``"mean"`` or a
            ``torch_geometric.nn.aggr.Aggregation`` (e.g. ``SoftmaxAggregation(learn=True)``).
        contact: Whether the layer has the contact edge relation.
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.

    Shapes:
        - **input:**
          node embeddings :math:`(|\mathcal{V}|, d)`,
          mesh edge indices :math:`(2, |\mathcal{E}^M|)`, mesh edge embeddings
          :math:`(|\mathcal{E}^M|, d)`,
          contact edge indices :math:`(2, |\mathcal{E}^C|)`, contact edge embeddings
          :math:`(|\mathcal{E}^C|, d)`, contact mask :math:`(|\mathcal{E}^C|)` *(optional;
          the three are* ``None`` *with* ``contact=False``*)*
        - **output:** node embeddings :math:`(|\mathcal{V}|, d)`, mesh edge embeddings
          :math:`(|\mathcal{E}^M|, d)`, contact edge embeddings :math:`(|\mathcal{E}^C|, d)`
          (``None`` with ``contact=False``)
    """

    def __init__(
        self,
        channels: int,
        mlp_channels: int = 128,
        aggr: str | Aggregation = "max",
        contact: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(channels, mlp_channels, aggr, **kwargs)
        self.contact = contact
        if contact:
            self.lin_contact, self.mlp_contact = self.residual(), self.mlp(3)
        self.lin_mesh, self.mlp_mesh = self.residual(), self.mlp(3)
        self.lin_node, self.mlp_node = self.residual(), self.mlp(3 if contact else 2)
        self.reset_parameters()

    def forward(
        self,
        x: Tensor,
        mesh_index: Edges,
        e_mesh: Tensor,
        contact_index: Edges | None = None,
        e_contact: OptTensor = None,
        contact_mask: OptTensor = None,
    ) -> tuple[Tensor, Tensor, OptTensor]:
        """Run one layer of eq. (1).

        Args:
            x: Node embeddings ``[N, d]``.
            mesh_index: Mesh edges ``[2, E]``, rows ``(source j, target i)``; a
                :class:`~torch_ampn.nn.SlottedEdgeIndex` aggregates by a dense reduction over
                its table instead of a scatter (same result; faster where the graph is fixed,
                as in a rollout).
            e_mesh: Mesh edge embeddings ``[E, d]``.
            contact_index: Contact edges ``[2, M]``, rows ``(source j, target i)``, plain or
                slotted (its table then leaves the masked slots out).
            e_contact: Contact edge embeddings ``[M, d]``.
            contact_mask: Optional ``BoolTensor[M]``: ``False`` marks an unused slot of a
                fixed-size contact table. Such edges do not contribute to the aggregation
                (exactly as if they were removed) and their output embeddings are zero;
                their indices must still be valid node indices (e.g. the node itself).

        Returns:
            ``(x, e_mesh, e_contact)`` with the shapes of the inputs (``e_contact`` ``None``
            without contact).
        """
        num_nodes = x.size(0)
        size = (num_nodes, num_nodes)
        # W e + f(k_i, k_j, e), the residual map sharing the MLP's product with e
        e_mesh = self.mlp_mesh.forward_edges(x, x, e_mesh, split_edges(mesh_index)[0], self.lin_mesh.weight)
        agg_mesh = self.aggregate_edges(mesh_index, e_mesh, size)  # [N, d]
        if not self.contact:
            return self.lin_node(x) + self.mlp_node(torch.cat([x, agg_mesh], dim=-1)), e_mesh, None
        if contact_index is None or e_contact is None:
            raise ValueError("IntraLevelConv(contact=True) needs contact_index and e_contact")
        contact_edges, contact_slots = split_edges(contact_index)  # [2, M], [N, D] or None
        e_contact = self.mlp_contact.forward_edges(x, x, e_contact, contact_edges, self.lin_contact.weight)
        if contact_slots is not None and isinstance(self.aggr, str):  # masked slots are left out
            agg_contact = self.aggregate_edges(contact_index, e_contact, size)
            if contact_mask is not None:
                e_contact = torch.where(contact_mask.unsqueeze(-1), e_contact, 0.0)
        elif contact_mask is None:
            agg_contact = self.propagate(contact_edges, edge_attr=e_contact, size=(num_nodes, num_nodes))
        else:
            # Send masked-out messages to a dummy node N, dropped afterwards: exact for
            # every aggregation (max, sum, mean) and free of data-dependent shapes.
            target = torch.where(contact_mask, contact_edges[1], num_nodes)  # [M]
            index = torch.stack([contact_edges[0], target])  # [2, M]
            agg_contact = self.propagate(index, edge_attr=e_contact, size=(num_nodes, num_nodes + 1))
            agg_contact = agg_contact[:num_nodes]  # [N, d]
            e_contact = torch.where(contact_mask.unsqueeze(-1), e_contact, 0.0)

        x = self.lin_node(x) + self.mlp_node(torch.cat([x, agg_contact, agg_mesh], dim=-1))  # [N, d]
        return x, e_mesh, e_contact
