"""What IntraLevelConv and InterLevelConv share: sizes, the aggregation, residual maps and MLPs."""

from __future__ import annotations

from torch import Tensor, nn
from torch_geometric.nn.aggr import Aggregation
from torch_geometric.nn.conv import MessagePassing

from torch_ampn.nn.mlp import LayerNormMLP

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
        **kwargs: Further arguments of :class:`torch_geometric.nn.conv.MessagePassing`.
    """

    def __init__(
        self, channels: int, mlp_channels: int = 128, aggr: str | Aggregation = "max", **kwargs
    ) -> None:
        super().__init__(aggr=check_aggr(aggr), **kwargs)
        self.channels = channels
        self.mlp_channels = mlp_channels

    def residual(self) -> nn.Linear:
        r"""A bias-free ``d -> d`` map :math:`\mathbf{W}`."""
        return nn.Linear(self.channels, self.channels, bias=False)

    def mlp(self, num_inputs: int) -> LayerNormMLP:
        """An MLP :math:`f` of ``num_inputs`` concatenated embeddings: ``[*, num_inputs d] -> [*, d]``."""
        return LayerNormMLP(num_inputs * self.channels, self.channels, self.mlp_channels)

    def reset_parameters(self) -> None:
        """Reset the aggregation, every residual map and every MLP."""
        super().reset_parameters()
        for module in self.children():
            if isinstance(module, (nn.Linear, LayerNormMLP)):
                module.reset_parameters()

    def message(self, edge_attr: Tensor) -> Tensor:
        """The message of edge ``(j, i)`` is its updated embedding: ``[E, d]``."""
        return edge_attr

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.channels}, mlp_channels={self.mlp_channels}, "
            f"aggr={self.aggr!r})"
        )
