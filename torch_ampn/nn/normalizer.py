"""Feature normalisation with statistics accumulated from the training set."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class Normalizer(nn.Module):
    r"""Per-feature standardisation :math:`(x - \mu) / \sigma` with statistics from training data.

    Statistics are accumulated explicitly with :meth:`update` (call it on training
    batches only), then frozen with :meth:`freeze`; :meth:`forward` / :meth:`normalize`
    never change them, so running it on validation or test data is safe. Count, mean and
    sum of squared deviations are kept in float64 buffers (saved in the state dict, so a
    checkpoint carries its normalisation).
    Before any update the normaliser is the identity (:math:`\mu = 0, \sigma = 1`).

    The eps guard: a feature whose standard deviation is below ``eps`` (a constant column,
    e.g. a one-hot class that never occurs, or tool motion on plies only) is divided by 1
    instead, i.e. only centred, so that an unseen value at test time is not blown up.

    With ``center=False`` the normaliser only scales, :math:`x / \sigma`: zero stays zero. The
    surrogate uses this for its target, so that a node the network leaves alone (output 0)
    does not move, rather than moving by the mean training residual.

    Args:
        num_features: Number of features ``F`` (the last dimension).
        eps: Standard deviations below this are replaced by 1.
        center: Subtract the mean (standardise) or only divide by the standard deviation.

    Shapes:
        - **input:** :math:`(*, F)`
        - **output:** :math:`(*, F)`
    """

    count: Tensor
    running_mean: Tensor
    running_m2: Tensor
    frozen: Tensor

    def __init__(self, num_features: int, eps: float = 1e-8, center: bool = True) -> None:
        super().__init__()
        self.num_features = num_features
        self.eps = eps
        self.center = center
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("running_mean", torch.zeros(num_features, dtype=torch.float64))
        self.register_buffer("running_m2", torch.zeros(num_features, dtype=torch.float64))
        self.register_buffer("frozen", torch.zeros((), dtype=torch.bool))

    def reset_statistics(self) -> None:
        """Forget all accumulated statistics (and unfreeze)."""
        self.count.zero_()
        self.running_mean.zero_()
        self.running_m2.zero_()
        self.frozen.fill_(False)

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        """Accumulate statistics of training samples ``x [*, F]`` (raises once frozen)."""
        if bool(self.frozen):
            raise RuntimeError("Normalizer is frozen: statistics come from training data only")
        if x.size(-1) != self.num_features:
            raise ValueError(f"expected {self.num_features} features, got {x.size(-1)}")
        x = x.detach().reshape(-1, self.num_features).to(torch.float64)  # [n_b, F]
        n_b = x.size(0)
        if n_b == 0:
            return
        # Chan et al.'s parallel merge of (count, mean, M2): stable for large means.
        mean_b = x.mean(0)
        m2_b = (x - mean_b).square().sum(0)
        n_a = self.count.clone()
        n = n_a + n_b
        delta = mean_b - self.running_mean
        self.running_mean += delta * (n_b / n)
        self.running_m2 += m2_b + delta.square() * (n_a * n_b / n)
        self.count.copy_(n)

    def freeze(self) -> Normalizer:
        """Stop accumulating: later :meth:`update` calls raise. Returns ``self``."""
        self.frozen.fill_(True)
        return self

    @property
    def mean(self) -> Tensor:
        """Per-feature mean ``[F]`` (float64; zeros before any update)."""
        return self.running_mean

    @property
    def std(self) -> Tensor:
        """Per-feature standard deviation ``[F]`` with the eps guard applied (float64)."""
        std = (self.running_m2 / self.count.clamp(min=1.0)).sqrt()  # population std
        return torch.where(std < self.eps, torch.ones_like(std), std)

    @property
    def shift(self) -> Tensor:
        """What :meth:`normalize` subtracts ``[F]``: the mean, or zeros when ``center=False``."""
        return self.running_mean if self.center else torch.zeros_like(self.running_mean)

    def normalize(self, x: Tensor) -> Tensor:
        """``(x - shift) / std``: ``[*, F] -> [*, F]`` in ``x``'s dtype."""
        return (x - self.shift.to(x.dtype)) / self.std.to(x.dtype)

    def denormalize(self, x: Tensor) -> Tensor:
        """``x * std + shift``, the inverse of :meth:`normalize`."""
        return x * self.std.to(x.dtype) + self.shift.to(x.dtype)

    def forward(self, x: Tensor) -> Tensor:
        """Same as :meth:`normalize`."""
        return self.normalize(x)

    def __repr__(self) -> str:
        center = "" if self.center else ", center=False"
        return f"{self.__class__.__name__}({self.num_features}, eps={self.eps}{center})"
