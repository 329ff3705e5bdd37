"""LayerNormMLP: the MLP inside every message passing layer of an AMPN."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class LayerNormMLP(nn.Module):
    r"""Two-layer perceptron with input layer normalisation, as in the seed paper.

    .. math::
        f(\mathbf{x}) = \mathbf{W}_2 \, \mathrm{SiLU}\left(\mathbf{W}_1 \,
        \mathrm{LayerNorm}(\mathbf{x}) + \mathbf{b}_1\right) + \mathbf{b}_2

    i.e. ``LayerNorm(in) -> Linear(in, hidden) -> SiLU -> Linear(hidden, out)``; with
    ``norm=False`` without the layer normalisation (the MLP then keeps the scale of its input,
    which a problem whose answer is proportional to its data needs: see :class:`~torch_ampn.nn.AMPN`).

    Args:
        in_channels: Size of each input sample.
        out_channels: Size of each output sample.
        hidden_channels: Width of the hidden layer (paper: 128).
        norm: Whether to normalise the input (paper: yes).

    Shapes:
        - **input:** :math:`(*, F_{in})`
        - **output:** :math:`(*, F_{out})`
    """

    def __init__(
        self, in_channels: int, out_channels: int, hidden_channels: int = 128, norm: bool = True
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.hidden_channels = hidden_channels
        self.norm = nn.LayerNorm(in_channels) if norm else None
        self.lin1 = nn.Linear(in_channels, hidden_channels)
        self.act = nn.SiLU()
        self.lin2 = nn.Linear(hidden_channels, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Reset all learnable parameters."""
        if self.norm is not None:
            self.norm.reset_parameters()
        self.lin1.reset_parameters()
        self.lin2.reset_parameters()

    def forward(self, x: Tensor) -> Tensor:
        """Apply the MLP: ``[*, in_channels] -> [*, out_channels]``."""
        return self.lin2(self.act(self.lin1(x if self.norm is None else self.norm(x))))

    def forward_edges(
        self,
        x_dst: Tensor,
        x_src: Tensor,
        edge_attr: Tensor,
        edge_index: Tensor,
        residual: Tensor | None = None,
    ) -> Tensor:
        r"""``self(cat([x_dst[i], x_src[j], edge_attr]))`` of every edge ``(j, i)``, uncatenated.

        The same function as the plain call on the gathered, concatenated input (up to float
        rounding), computed the way a message-passing layer can afford: ``LayerNorm`` and the
        first linear layer are split into the three input blocks, so the node blocks are
        multiplied once per *node* and gathered per edge with their mean and centred sum of
        squares (the layer-norm statistics :math:`\mu, \sigma^2` of the concatenation follow
        from those by the pairwise variance formula, without cancellation). Per edge that
        leaves one ``[F_edge, hidden]`` product instead of a ``[F_dst + F_src + F_edge, hidden]``
        one, and no ``[E, F]`` concatenation.

        Args:
            x_dst: Target node features ``[N_dst, F_dst]``.
            x_src: Source node features ``[N_src, F_src]`` (may be ``x_dst``).
            edge_attr: Edge features ``[E, F_edge]``; ``F_dst + F_src + F_edge = in_channels``.
            edge_index: ``[2, E]``, rows ``(source j, target i)``.
            residual: Optional weight ``[out_channels, F_edge]`` of a bias-free linear map of
                ``edge_attr`` to add to the output (the residual map of a message-passing
                layer); it shares one matrix product with the first layer's edge block.

        Returns:
            ``[E, out_channels]``.
        """
        f_dst, f_src, f_edge = x_dst.size(-1), x_src.size(-1), edge_attr.size(-1)
        if f_dst + f_src + f_edge != self.in_channels:
            raise ValueError(
                f"feature sizes {f_dst} + {f_src} + {f_edge} do not add up to in_channels={self.in_channels}"
            )
        if self.norm is None:
            return self._forward_edges_plain(x_dst, x_src, edge_attr, edge_index, residual)
        weight = self.lin1.weight * self.norm.weight  # [H, F]: W_1 diag(gamma)
        # W_1 diag(gamma) (c - mean(c)) = W' c with a rank-one correction of the weight:
        weight = weight - weight.sum(-1, keepdim=True) / self.in_channels  # [H, F]
        w_dst, w_src, w_edge = weight.split([f_dst, f_src, f_edge], dim=-1)
        if x_src is x_dst:  # one product for both ends of the edges
            z_dst, z_src = (x_dst @ torch.cat([w_dst, w_src]).t()).split(weight.size(0), dim=-1)  # [N, H] x2
            stats_dst = stats_src = _row_stats(x_dst)  # [N, 2]
        else:
            z_dst, stats_dst = x_dst @ w_dst.t(), _row_stats(x_dst)  # [N_dst, H], [N_dst, 2]
            z_src, stats_src = x_src @ w_src.t(), _row_stats(x_src)  # [N_src, H], [N_src, 2]
        src, dst = edge_index
        if residual is None:
            z_edge = edge_attr @ w_edge.t()  # [E, H]
        else:  # one product for both maps of the edge features
            z_edge, res = (edge_attr @ torch.cat([w_edge, residual]).t()).split(  # [E, H], [E, out]
                [weight.size(0), residual.size(0)], dim=-1
            )
        blocks = [
            (f_dst, stats_dst.index_select(0, dst)),
            (f_src, stats_src.index_select(0, src)),
            (f_edge, _row_stats(edge_attr)),
        ]  # (size, [E, 2]) per block
        var = _pooled_variance(blocks, self.in_channels)  # [E, 1]
        bias = self.lin1.bias + self.lin1.weight @ self.norm.bias  # [H]: W_1 beta + b_1
        z = z_dst.index_select(0, dst)  # [E, H]
        if torch.is_grad_enabled():
            z = z + z_src.index_select(0, src) + z_edge
            hidden = self.act(z * torch.rsqrt(var + self.norm.eps) + bias)  # [E, H]
        else:  # the same operations in place: no autograd to keep inputs for, fewer [E, H] buffers
            z = z.add_(z_src.index_select(0, src)).add_(z_edge)
            hidden = nn.functional.silu(z.mul_(var.add_(self.norm.eps).rsqrt_()).add_(bias), inplace=True)
        out = self.lin2(hidden)  # [E, out]
        return out if residual is None else out + res

    def _forward_edges_plain(
        self, x_dst: Tensor, x_src: Tensor, edge_attr: Tensor, edge_index: Tensor, residual: Tensor | None
    ) -> Tensor:
        """:meth:`forward_edges` without the layer normalisation: ``[E, out_channels]``."""
        f_dst, f_src = x_dst.size(-1), x_src.size(-1)
        w_dst, w_src, w_edge = self.lin1.weight.split([f_dst, f_src, edge_attr.size(-1)], dim=-1)
        src, dst = edge_index
        if residual is None:
            z_edge = edge_attr @ w_edge.t()  # [E, H]
        else:
            z_edge, res = (edge_attr @ torch.cat([w_edge, residual]).t()).split(
                [w_edge.size(0), residual.size(0)], dim=-1
            )  # [E, H], [E, out]
        z = (x_dst @ w_dst.t()).index_select(0, dst) + (x_src @ w_src.t()).index_select(0, src) + z_edge
        out = self.lin2(self.act(z + self.lin1.bias))  # [E, out]
        return out if residual is None else out + res

    def __repr__(self) -> str:
        norm = "" if self.norm is not None else ", norm=False"
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
            f"hidden_channels={self.hidden_channels}{norm})"
        )


def _row_stats(x: Tensor) -> Tensor:
    """``[mean(x), sum((x - mean(x))^2)]`` per row: ``[N, F] -> [N, 2]``."""
    mean = x.mean(-1, keepdim=True)  # [N, 1]
    return torch.cat([mean, (x - mean).square().sum(-1, keepdim=True)], dim=-1)


def _pooled_variance(blocks: list[tuple[int, Tensor]], total: int) -> Tensor:
    """Population variance of a concatenation from each block's ``(size, [mean, centred sum of squares])``.

    Chan et al.'s pairwise formula, so no ``E[x^2] - E[x]^2`` cancellation when the
    features have a large mean. Each block's statistics are ``[E, 2]``; returns ``[E, 1]``.
    """
    mean = sum(n * stats[:, :1] for n, stats in blocks) / total  # [E, 1]
    m2 = sum(stats[:, 1:] + n * (stats[:, :1] - mean).square() for n, stats in blocks)  # [E, 1]
    return m2 / total
