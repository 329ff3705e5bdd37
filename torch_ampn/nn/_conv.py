"""What IntraLevelConv and InterLevelConv share: sizes, the aggregation, residual maps and MLPs."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch_geometric.nn.aggr import Aggregation
from torch_geometric.nn.conv import MessagePassing

from torch_ampn.nn.mlp import LayerNormMLP
from torch_ampn.nn.slots import Edges, split_edges

AGGREGATIONS = ("max", "sum", "mean")


def check_aggr(aggr: str | Aggregation) -> str | Aggregation:
    """``aggr`` if it is a PyG ``Aggregation`` or one of :data:`AGGREGATIONS`; else ``ValueError``."""
    if isinstance(aggr, Aggregation):
        return aggr
    if aggr not in AGGREGATIONS:
        raise ValueError(f"aggr must be one of {AGGREGATIONS} or a torch_geometric Aggregation, got {aggr!r}")
    return aggr


class EmbeddingConv(MessagePassing):
    """Base of the AMPN layers: node and edge embeddings of size ``channels``, messages = edge embeddings.

    Subclasses build their residual maps with :meth:`residual` and their MLPs with :meth:`mlp`;
    :meth:`reset_parameters` resets all of them.

    Args:
        channels: Size :math:`d` of node and edge embeddings.
        mlp_channels: Hidden width of the MLPs (paper: 128).
        aggr: ``"max"``, ``"sum"``, ``"mean"`` or a ``torch_geometric.nn.aggr.Aggregation``.
        mlp_norm: Whether the MLPs normalise their input (:class:`~torch_ampn.nn.LayerNormMLP`).
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.
    """

    def __init__(
        self,
        channels: int,
        mlp_channels: int = 128,
        aggr: str | Aggregation = "max",
        mlp_norm: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(aggr=check_aggr(aggr), **kwargs)
        self.channels = channels
        self.mlp_channels = mlp_channels
        self.mlp_norm = bool(mlp_norm)

    def residual(self) -> nn.Linear:
        r"""A bias-free ``d -> d`` map :math:`\mathbf{W}`."""
        return nn.Linear(self.channels, self.channels, bias=False)

    def mlp(self, num_inputs: int) -> LayerNormMLP:
        """An MLP :math:`f` of ``num_inputs`` concatenated embeddings: ``[*, num_inputs d] -> [*, d]``."""
        return LayerNormMLP(num_inputs * self.channels, self.channels, self.mlp_channels, norm=self.mlp_norm)

    def reset_parameters(self) -> None:
        """Reset the aggregation, every residual map and every MLP."""
        super().reset_parameters()
        for module in self.children():
            if isinstance(module, (nn.Linear, LayerNormMLP)):
                module.reset_parameters()

    def aggregate_edges(self, edges: Edges, edge_attr: Tensor, size: tuple[int, int]) -> Tensor:
        """Aggregate the edge embeddings at their targets, ``[N_t, d]``.

        Edges that carry their aggregation table (a :class:`~torch_ampn.nn.SlottedEdgeIndex`;
        used for ``"max"``, ``"sum"`` and ``"mean"``) are reduced densely over each target's
        slots, others with PyG's ``propagate``. Both give the same result (up to summation
        order); a target without incoming edges gets zeros.
        """
        edge_index, slots = split_edges(edges)
        if slots is None or not isinstance(self.aggr, str):
            return self.propagate(edge_index, edge_attr=edge_attr, size=size)
        if edge_attr.size(0) == 0:  # no edge at all (static shape: decided at trace time)
            return edge_attr.new_zeros(size[1], edge_attr.size(1))
        # One slot column at a time: each step gathers whole rows (contiguous channels), which a
        # compiled kernel vectorises; a reduction over a [N_t, D, d] gather would be vectorised
        # over the D slots instead, with a strided load per channel (4x slower on a CPU).
        out = count = None
        for column in slots.unbind(dim=1):  # [N_t] each; D columns, unrolled when compiled
            used = (column >= 0).unsqueeze(-1)  # [N_t, 1]
            rows = edge_attr.index_select(0, column.clamp(min=0))  # [N_t, d]
            count = used.long() if count is None else count + used  # [N_t, 1]
            if self.aggr == "max":
                rows = torch.where(used, rows, float("-inf"))
                out = rows if out is None else torch.maximum(out, rows)
            else:
                rows = torch.where(used, rows, 0.0)
                out = rows if out is None else out + rows
        if self.aggr == "max":
            return torch.where(count > 0, out, 0.0)  # targets without edges: zeros
        if self.aggr == "sum":
            return out
        return out / count.clamp(min=1).to(out.dtype)

    def message(self, edge_attr: Tensor) -> Tensor:
        """The message of edge ``(j, i)`` is its updated embedding: ``[E, d]``."""
        return edge_attr

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.channels}, mlp_channels={self.mlp_channels}, "
            f"aggr={self.aggr!r})"
        )
