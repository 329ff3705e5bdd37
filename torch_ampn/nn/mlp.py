"""The MLP used inside every message passing layer of an AMPN."""

from __future__ import annotations

from torch import Tensor, nn


class MLP(nn.Module):
    r"""Two-layer perceptron with input layer normalisation, as in the seed paper.

    .. math::
        f(\mathbf{x}) = \mathbf{W}_2 \, \mathrm{SiLU}\left(\mathbf{W}_1 \,
        \mathrm{LayerNorm}(\mathbf{x}) + \mathbf{b}_1\right) + \mathbf{b}_2

    i.e. ``LayerNorm(in) -> Linear(in, hidden) -> SiLU -> Linear(hidden, out)``.

    Args:
        in_channels: Size of each input sample.
        out_channels: Size of each output sample.
        hidden_channels: Width of the hidden layer (paper: 128).

    Shapes:
        - **input:** :math:`(*, F_{in})`
        - **output:** :math:`(*, F_{out})`
    """

    def __init__(self, in_channels: int, out_channels: int, hidden_channels: int = 128) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.hidden_channels = hidden_channels
        self.norm = nn.LayerNorm(in_channels)
        self.lin1 = nn.Linear(in_channels, hidden_channels)
        self.act = nn.SiLU()
        self.lin2 = nn.Linear(hidden_channels, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Reset all learnable parameters."""
        self.norm.reset_parameters()
        self.lin1.reset_parameters()
        self.lin2.reset_parameters()

    def forward(self, x: Tensor) -> Tensor:
        """Apply the MLP: ``[*, in_channels] -> [*, out_channels]``."""
        return self.lin2(self.act(self.lin1(self.norm(x))))

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
            f"hidden_channels={self.hidden_channels})"
        )
