"""The reach benchmark's networks, built at (nearly) equal parameter counts.

Every network maps a hierarchy (:class:`~torch_ampn.hierarchy.HierarchicalData`, the flat ones
read only ``l0``) to ``[N, out]``:

* ``ampn``: :class:`~torch_ampn.nn.AMPN` with the package's defaults (the reference width ``d``);
* ``ampn_paper``: the seed paper's V-cycle (max aggregation, layer-normalised MLPs, no input
  normalisation) at the same width, and ``ampn_*`` variants with one lever changed (see
  :data:`AMPN_VARIANTS`);
* ``flat``: the MeshGraphNet-style processor (``num_levels=1``, Pre + Solve + Post, the same
  defaults), widened to the AMPN's parameter count;
* ``flat_deep``: a flat processor with as many layers as the AMPN makes layer calls per
  prediction (its V-cycle reuses each stack on every level), narrowed to the same count;
* ``graph_unet``: PyG's ``GraphUNet`` (GCN layers, top-k pooling), width matched.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch_geometric.nn import GraphUNet

from torch_ampn.hierarchy import HierarchicalData
from torch_ampn.nn import AMPN

#: The generic AMPN's layer stacks in this benchmark (the paper's: 3, 2, 5, 3, 2).
STACKS = dict(pre_layers=2, down_layers=1, solve_layers=4, post_layers=2, up_layers=1)
#: AMPN options of each variant, over the package's defaults (``ampn``).
AMPN_VARIANTS: dict[str, dict] = {
    "ampn": {},
    "ampn_paper": dict(aggr="max", mlp_norm=True, transfer_weights=False, coarse_inputs="none"),
    "ampn_mlp_norm": dict(mlp_norm=True),
    "ampn_max": dict(aggr="max"),
    "ampn_mean": dict(aggr="mean"),
    "ampn_normalize": dict(normalize=True),
    "ampn_no_transfer_weights": dict(transfer_weights=False),
    "ampn_no_restrict": dict(coarse_inputs="none"),
    "ampn_plain": dict(transfer_weights=False, coarse_inputs="none"),
}


def count(model: nn.Module) -> int:
    """Number of parameters."""
    return sum(p.numel() for p in model.parameters())


class Flat(nn.Module):
    """A flat network on ``l0`` of a hierarchy: an :class:`AMPN` with ``num_levels=1``."""

    def __init__(self, model: AMPN) -> None:
        super().__init__()
        self.model = model

    def forward(self, data: HierarchicalData) -> Tensor:
        return self.model(data)  # [N, out]: reads l0 only


class UNet(nn.Module):
    """PyG's ``GraphUNet`` on ``l0``'s mesh edges; node inputs standardised like AMPN(normalize=True)."""

    def __init__(self, in_channels: int, out_channels: int, hidden: int, depth: int) -> None:
        super().__init__()
        self.net = GraphUNet(in_channels, hidden, out_channels, depth=depth, pool_ratios=0.5)
        self.register_buffer("mean", torch.zeros(in_channels))
        self.register_buffer("std", torch.ones(in_channels))

    def fit_inputs(self, xs: list[Tensor]) -> None:
        """Standardise the inputs with these training samples' statistics."""
        x = torch.cat(xs)
        self.mean.copy_(x.mean(0))
        self.std.copy_(torch.where(x.std(0) > 1e-8, x.std(0), 1.0))

    def forward(self, data: HierarchicalData) -> Tensor:
        x = (data["l0"].x - self.mean) / self.std
        return self.net(x, data["l0", "mesh", "l0"].edge_index)  # [N, out]


def _match(build: Callable[[int], nn.Module], target: int, lo: int = 4, hi: int = 512) -> nn.Module:
    """The network of width ``w`` in ``[lo, hi]`` whose parameter count is closest to ``target``."""
    while hi - lo > 1:  # the count grows with the width: bisect to the last width at or below the target
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if count(build(mid)) <= target else (lo, mid)
    return min((build(lo), build(hi)), key=lambda m: abs(count(m) - target))


def layer_calls(num_levels: int) -> int:
    """Layer calls of one AMPN prediction with :data:`STACKS`: Pre and Down, Up and Post per level."""
    s = STACKS
    down = (num_levels - 1) * (s["pre_layers"] + s["down_layers"] + s["up_layers"] + s["post_layers"])
    return down + s["pre_layers"] + s["solve_layers"] + s["post_layers"]


def build(
    name: str,
    in_channels: int,
    out_channels: int,
    edge_channels: int,
    num_levels: int,
    width: int,
    common: dict | None = None,
) -> nn.Module:
    """The network ``name`` at the parameter count of the ``ampn`` of width ``width``.

    ``common``: :class:`AMPN` options given to every AMPN-built network (the AMPNs and both flat
    ones), e.g. ``{"normalize": True}``; the variant's own options override them.
    """

    def ampn(d: int, **options) -> AMPN:
        kw = {"num_levels": num_levels, **STACKS, **(common or {}), **options}
        return AMPN(in_channels, out_channels, edge_channels, hidden_channels=d, mlp_channels=d, **kw)

    reference = count(ampn(width))
    if name in AMPN_VARIANTS:
        return ampn(width, **AMPN_VARIANTS[name])
    if name == "flat":
        return _match(lambda d: Flat(ampn(d, num_levels=1)), reference)
    if name == "flat_deep":
        depth = layer_calls(num_levels)
        pre = post = depth // 4
        layers = dict(pre_layers=pre, solve_layers=depth - pre - post, post_layers=post)
        return _match(lambda d: Flat(ampn(d, num_levels=1, **layers)), reference)
    if name == "graph_unet":
        depth = max(num_levels, 2)
        return _match(lambda d: UNet(in_channels, out_channels, d, depth), reference, hi=1024)
    raise ValueError(
        f"unknown network {name!r}: one of {[*AMPN_VARIANTS, 'flat', 'flat_deep', 'graph_unet']}"
    )
