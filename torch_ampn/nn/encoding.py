"""Sinusoidal (Fourier) encodings of small integer indices: hierarchy level and diffusion step."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class FourierLevelEncoding(nn.Module):
    r"""Sinusoidal encoding of an integer index such as the hierarchy level :math:`l`.

    .. math::
        \gamma(l) = \left[\sin(\omega_0 l), \dots, \sin(\omega_{F-1} l),
        \cos(\omega_0 l), \dots, \cos(\omega_{F-1} l)\right],
        \qquad \omega_k = \pi \, 2^{-k}\, \frac{1}{s}

    with ``F = num_frequencies`` and scale :math:`s` = ``max_index``: the highest frequency
    :math:`\pi / s` separates neighbouring indices, the lowest ones vary slowly over
    ``0 .. max_index``, so every index in that range has a distinct code. AMPN concatenates
    :math:`\gamma(l)` to the input features of every node of level :math:`l` (the same layers
    run on every level, the code tells them which one), and the same class encodes the
    diffusion step in ROBIN mode. The frequencies are a buffer (not learned).

    Args:
        num_frequencies: Number of frequencies :math:`F` (output size ``2 F``).
        max_index: Largest index to be told apart (levels: a few; diffusion steps: ``K``).

    Shapes:
        - **input:** an ``int``/``float`` (one index) or a tensor of indices :math:`(*)`
        - **output:** :math:`(2F)` or :math:`(*, 2F)`
    """

    frequencies: Tensor

    def __init__(self, num_frequencies: int = 4, max_index: float = 8.0) -> None:
        super().__init__()
        if num_frequencies < 1:
            raise ValueError(f"num_frequencies must be >= 1, got {num_frequencies}")
        if max_index <= 0:
            raise ValueError(f"max_index must be positive, got {max_index}")
        self.num_frequencies = num_frequencies
        self.max_index = max_index
        k = torch.arange(num_frequencies, dtype=torch.float32)
        self.register_buffer("frequencies", math.pi * torch.pow(2.0, -k) / max_index, persistent=False)

    @property
    def out_channels(self) -> int:
        """Size of the encoding, ``2 * num_frequencies``."""
        return 2 * self.num_frequencies

    def forward(self, index: Tensor | int | float) -> Tensor:
        """Encode ``index`` (a number or a tensor of any shape ``[*]``) as ``[*, 2F]`` (float32)."""
        if isinstance(index, Tensor):
            angle = index.to(self.frequencies.dtype).unsqueeze(-1) * self.frequencies  # [*, F]
        else:
            angle = self.frequencies * float(index)  # [F]
        return torch.cat([angle.sin(), angle.cos()], dim=-1)

    def __repr__(self) -> str:
        return f"{self.__class__.__name__}({self.num_frequencies}, max_index={self.max_index})"
