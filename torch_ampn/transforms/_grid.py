"""A cell grid for exact fixed-radius and k-nearest neighbour search in pure PyTorch.

Private helper of :mod:`torch_ampn.transforms._grid_search`. Every node belongs to a *group*
(for contact edges: a (graph, component) pair). Nodes are sorted by an integer key made of
their group, the cells of their *column* (cubic cells of edge ``h`` along one or two box
axes) and a fine sub-cell along the *run* axis, so that the nodes of one group, one column
and an interval along the run axis form one contiguous run of the sorted nodes. A query
reads a box of ``+-rho`` columns around its node, one run per column, each cut to the chord
of the search ball. Run ends are looked up in a dense table of key starts when it is small
enough, else by binary search over the sorted keys; both give the same result. Nothing here
builds an ``N x N`` matrix: work and memory grow with the number of candidates, processed
in chunks.

Distances are computed in float64 as ``dx * dx + dy * dy + dz * dz`` whatever the input
precision, so that results and ties do not depend on it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

#: Slack (in cell units) that keeps every floating-point cell test conservative.
EPS_CELLS = 1e-6
#: Largest number of cells along one axis (float64 cell coordinates stay exact far beyond it).
MAX_AXIS_CELLS = 1 << 21
#: Keys must stay well inside int64.
MAX_KEYS = 1 << 62
#: The dense table of cell starts is used while it has at most max(this, 8 N) entries.
DENSE_TABLE_MIN = 1 << 22
#: Sub-cells per cell along the run axis (a power of two keeps the scaling exact).
SUBDIV = 8
#: Default chunk sizes: (query, column) ranges and candidate pairs held at once (about
#: 0.2 GB of temporaries at most on the CPU); CUDA devices take ``CUDA_CHUNK_SCALE`` times
#: more (about 1.6 GB), to launch fewer kernels.
MAX_RANGES = 1 << 20
MAX_PAIRS = 1 << 21
CUDA_CHUNK_SCALE = 8


def cells_needed(radius: float, cell_size: float) -> int:
    """Smallest ``m`` such that a box of ``+-m`` cells around a node covers the ball of ``radius``."""
    return max(1, math.ceil(radius / cell_size + EPS_CELLS))


def coverage(rho: int, cell_size: float) -> float:
    """Radius of the ball around a node that its box of ``+-rho`` cells is sure to contain.

    A node outside the box is more than ``rho`` cells away along some axis, hence farther
    than ``rho * cell_size``; the slack keeps this true under rounding.
    """
    return (rho - EPS_CELLS) * cell_size


@dataclass
class CandidateChunk:
    """Candidate pairs of a run of consecutive queries ``start .. stop - 1``.

    Attributes:
        start: First query of the run.
        stop: One past the last query of the run.
        query: ``[P]`` query of each pair, counted from ``start``.
        source: ``[P]`` source node of each pair.
        dist2: ``[P]`` squared distance (float64) between source and query node.
    """

    start: int
    stop: int
    query: Tensor
    source: Tensor
    dist2: Tensor


class CellGrid:
    """Nodes sorted into a grid of cells, one grid per group, read in runs along one axis.

    The grid's axes are the coordinate axes ordered by decreasing extent of the point cloud.
    Two layouts:

    * *thin* (every group spans at most one cell along the thinnest axis: plates, shells,
      laminates): cells are columns over the widest axis (edge ``h``), runs go along the
      middle axis and the thinnest axis is ignored (a group has few nodes across it); the
      distance from a node to a group's slab along it bounds the search (:meth:`floor2`);
    * *columns* (otherwise): cells are columns over the two widest axes, runs go along the
      thinnest one.

    Along the run axis nodes are keyed by sub-cells ``h / SUBDIV``, so a run reads the exact
    chord of the search ball through its column (rounded out to a sub-cell), not whole cells.

    Args:
        pos: ``[N, 3]`` float64 node positions (finite).
        group: ``[N]`` long group id of each node, in ``0 .. num_groups - 1``.
        num_groups: Number of groups ``G``.
        cell_size: Requested cell edge ``h > 0``. It is doubled until the grid fits int64
            keys (only for extreme extents relative to ``h``); read the one used from
            :attr:`cell_size`.
        reach: Largest search radius that will be asked for; the box axes are padded by
            ``cells_needed(reach, h)`` empty cells on both sides so that no box wraps.
    """

    def __init__(self, pos: Tensor, group: Tensor, num_groups: int, cell_size: float, reach: float) -> None:
        self.num_groups = max(int(num_groups), 1)
        lo = pos.min(0).values
        extent = (pos.max(0).values - lo).tolist()
        axes = sorted(range(3), key=lambda d: -extent[d])
        rel = (pos - lo)[:, axes]  # [N, 3] in grid axes, widest first
        self.slab = _group_slabs(rel[:, 2], group, self.num_groups)  # ([G], [G]) along the thinnest
        self.thin = bool((self.slab[1] - self.slab[0]).max() <= cell_size)
        self.depth = rel[:, 2].contiguous()  # [N] coordinate along the thinnest axis
        self.num_box = 1 if self.thin else 2  # axes searched box-wise; the next one is read in runs
        extent = [extent[d] for d in axes][: self.num_box + 1]
        self.cell_size, self.pad = self._fit_cell_size(extent, float(cell_size), float(reach))
        self.unit = rel[:, : self.num_box + 1] / self.cell_size  # [N, B + 1] in cells
        self.unit[:, : self.num_box] += self.pad
        self.cell = torch.floor(self.unit).long()
        top = self.cell.max(0).values.tolist()
        self.dims = [t + 1 + self.pad for t in top[: self.num_box]] + [(top[-1] + 1) * SUBDIV]
        key = self._key(group, self.cell[:, : self.num_box], torch.floor(self.unit[:, -1] * SUBDIV).long())
        self.sorted_key, self.order = torch.sort(key, stable=True)
        self.coords = tuple(pos[:, d].contiguous() for d in range(3))  # per axis, node order
        self.sorted_coords = tuple(c.index_select(0, self.order) for c in self.coords)
        self.num_keys = self.num_groups * math.prod(self.dims)
        self.start = None
        if self.num_keys <= max(DENSE_TABLE_MIN, 8 * pos.size(0)):
            self.start = self._dense_starts(key)

    def _fit_cell_size(self, extent: list[float], h: float, reach: float) -> tuple[float, int]:
        while True:
            pad = cells_needed(reach, h)
            dims = [math.floor(e / h) + 2 + 2 * pad for e in extent[:-1]]
            dims.append((math.floor(extent[-1] / h) + 2) * SUBDIV)
            if max(dims) <= MAX_AXIS_CELLS and self.num_groups * math.prod(dims) < MAX_KEYS:
                return h, pad
            h *= 2.0

    def _key(self, group: Tensor, box: Tensor, sub: Tensor) -> Tensor:
        """Sort key of box cells ``box`` ``[..., B]``, run sub-cells ``sub`` and ``group``."""
        key = group
        for axis in range(self.num_box):
            key = key * self.dims[axis] + box[..., axis]
        return key * self.dims[-1] + sub

    def _dense_starts(self, key: Tensor) -> Tensor:
        counts = torch.bincount(key, minlength=self.num_keys)
        start = torch.zeros(self.num_keys + 1, dtype=torch.long, device=key.device)
        torch.cumsum(counts, 0, out=start[1:])
        return start

    def rank(self, key: Tensor) -> Tensor:
        """Number of nodes whose key is smaller than ``key`` (any shape, ``0 <= key <= num_keys``)."""
        if self.start is not None:
            return self.start.index_select(0, key.reshape(-1)).view(key.shape)
        return torch.searchsorted(self.sorted_key, key)

    def floor2(self, node: Tensor, group: Tensor) -> Tensor:
        """Lower bound on the squared distance from each ``node`` to any node of ``group``.

        In the thin layout a group lies in a slab across the ignored (thinnest) axis, so its
        nodes are at least the node's distance to that slab away (less slack); ``0`` in the
        column layout.

        Args:
            node: ``[Q]`` query nodes.
            group: ``[Q]`` groups.

        Returns:
            ``[Q]`` float64.
        """
        if not self.thin:
            return torch.zeros(node.shape, dtype=self.depth.dtype, device=node.device)
        depth = self.depth.index_select(0, node)
        gap = torch.maximum(
            self.slab[0].index_select(0, group) - depth, depth - self.slab[1].index_select(0, group)
        )
        gap = (gap - EPS_CELLS * self.cell_size).clamp(min=0.0)
        return gap * gap

    def column_ranges(self, node: Tensor, group: Tensor, rho: int, bound2: Tensor) -> tuple[Tensor, Tensor]:
        """Runs of sorted nodes of ``group`` that may lie within ``sqrt(bound2)`` of ``node``.

        Covers the box of ``+-rho`` cells around each query node, less the columns farther
        than the bound, and in each column the chord of the ball along the run axis
        (conservatively, with slack), clipped to the box.

        Args:
            node: ``[Q]`` query nodes.
            group: ``[Q]`` group searched by each query.
            rho: Half-width of the box in cells, ``1 <= rho <= pad``.
            bound2: ``[Q]`` float64 squared search radius of each query.

        Returns:
            ``(lo, hi)``, both ``[Q, W]`` with ``W = (2 rho + 1) ** B`` columns (``B`` box
            axes): sorted positions ``lo <= p < hi``.
        """
        unit, cell = self.unit.index_select(0, node), self.cell.index_select(0, node)  # [Q, B + 1]
        off = torch.arange(-rho, rho + 1, device=node.device)
        rest2 = ((bound2 - self.floor2(node, group)) / self.cell_size**2)[:, None]  # squared cells left
        column = group[:, None]
        for axis in range(self.num_box):
            gap = self._gap(unit[:, axis : axis + 1] - cell[:, axis : axis + 1], off)  # [Q, 2 rho + 1]
            rest2 = (rest2[:, :, None] - (gap * gap)[:, None, :]).flatten(1)
            column = (
                column[:, :, None] * self.dims[axis] + (cell[:, axis : axis + 1] + off)[:, None, :]
            ).flatten(1)
        reach = torch.sqrt(rest2.clamp(min=0.0)) + EPS_CELLS
        run, run_cell = unit[:, -1:], cell[:, -1:]  # the run stays inside the box too
        first = ((run_cell - rho) * SUBDIV).clamp(min=0)
        last = ((run_cell + rho + 1) * SUBDIV - 1).clamp(max=self.dims[-1] - 1)
        sub_lo = torch.maximum(torch.floor((run - reach) * SUBDIV).long(), first)
        sub_hi = torch.minimum(torch.floor((run + reach) * SUBDIV).long(), last)
        sub_hi = torch.where(rest2 >= 0, sub_hi, sub_lo - 1)  # an empty run
        base = column * self.dims[-1]
        return self.rank(base + sub_lo), self.rank(base + sub_hi + 1)

    @staticmethod
    def _gap(frac: Tensor, d: Tensor) -> Tensor:
        """Distance in cells from a point at ``frac`` in its cell to the cell ``d`` away (>= 0)."""
        gap = torch.where(d > 0, d - frac, frac - d - 1)
        return (gap - EPS_CELLS).clamp(min=0.0)

    def candidates(
        self,
        node: Tensor,
        group: Tensor,
        rho: int,
        bound2: Tensor,
        exclude_self: bool = False,
        max_ranges: int | None = None,
        max_pairs: int | None = None,
    ) -> Iterator[CandidateChunk]:
        """All pairs (query ``q``, node ``j`` of ``group[q]``) within ``sqrt(bound2[q])`` of ``node[q]``.

        Yields them in chunks of consecutive queries; within a chunk pairs are grouped by query.

        Args:
            node: ``[Q]`` query nodes.
            group: ``[Q]`` group searched by each query.
            rho: Half-width in cells of the box searched; it must cover ``sqrt(bound2)``
                for the result to be complete (:func:`coverage`).
            bound2: ``[Q]`` float64 squared radius, inclusive.
            exclude_self: Drop pairs whose source is the query node.
            max_ranges: Most (query, column) ranges held at once (default :data:`MAX_RANGES`).
            max_pairs: Most candidate pairs held at once, a single query may exceed it
                (default :data:`MAX_PAIRS`).
        """
        scale = CUDA_CHUNK_SCALE if node.is_cuda else 1
        max_ranges = max_ranges or MAX_RANGES * scale
        max_pairs = max_pairs or MAX_PAIRS * scale
        width = (2 * rho + 1) ** self.num_box
        step = max(1, max_ranges // width)
        for begin in range(0, node.numel(), step):
            end = min(begin + step, node.numel())
            lo, hi = self.column_ranges(node[begin:end], group[begin:end], rho, bound2[begin:end])
            per_query = (hi - lo).sum(1)
            for a, b in _split_by_budget(per_query, max_pairs):
                yield self._pairs(node, bound2, lo[a:b], hi[a:b], begin + a, begin + b, exclude_self)

    def _pairs(
        self, node: Tensor, bound2: Tensor, lo: Tensor, hi: Tensor, start: int, stop: int, exclude_self: bool
    ) -> CandidateChunk:
        width = lo.size(1)
        owner, sorted_pos = expand_ranges(lo.reshape(-1), hi.reshape(-1))
        query = torch.div(owner, width, rounding_mode="floor")
        target = node[start:stop]
        dist2 = None
        for sorted_c, c in zip(self.sorted_coords, self.coords, strict=True):
            d = sorted_c.index_select(0, sorted_pos) - c.index_select(0, target).index_select(0, query)
            dist2 = d * d if dist2 is None else dist2 + d * d
        keep = dist2 <= bound2[start:stop].index_select(0, query)
        source = self.order.index_select(0, sorted_pos)
        if exclude_self:
            keep &= source != target.index_select(0, query)
        keep = keep.nonzero().squeeze(1)
        return CandidateChunk(
            start,
            stop,
            query.index_select(0, keep),
            source.index_select(0, keep),
            dist2.index_select(0, keep),
        )


def _group_slabs(coord: Tensor, group: Tensor, num_groups: int) -> tuple[Tensor, Tensor]:
    """Smallest and largest ``coord`` (``[N]``) of every group, ``[G]`` each (empty: ``0, 0``)."""
    bottom = torch.full((num_groups,), math.inf, dtype=coord.dtype, device=coord.device)
    top = torch.full((num_groups,), -math.inf, dtype=coord.dtype, device=coord.device)
    bottom.scatter_reduce_(0, group, coord, "amin")
    top.scatter_reduce_(0, group, coord, "amax")
    empty = bottom > top
    return bottom.masked_fill(empty, 0.0), top.masked_fill(empty, 0.0)


def squared_distance(pos: Tensor, source: Tensor, target: Tensor) -> Tensor:
    """``|pos[source] - pos[target]|**2`` as ``dx * dx + dy * dy + dz * dz`` (in ``pos.dtype``)."""
    d = pos[source] - pos[target]
    return d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]


def expand_ranges(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Concatenate the integer ranges ``lo[r] .. hi[r] - 1``.

    Returns:
        ``(owner, value)``, both ``[sum(hi - lo)]``: the range each element comes from and
        the element itself, in order.
    """
    count = hi - lo
    total = int(count.sum())
    owner = torch.repeat_interleave(torch.arange(lo.numel(), device=lo.device), count, output_size=total)
    shift = lo - (torch.cumsum(count, 0) - count)
    return owner, torch.arange(total, device=lo.device) + shift.index_select(0, owner)


def _split_by_budget(count: Tensor, budget: int) -> list[tuple[int, int]]:
    """Split ``0 .. len(count)`` into runs whose summed ``count`` stays within ``budget``.

    A single item above the budget forms a run of its own.
    """
    n = count.numel()
    if n == 0:
        return []
    total = int(count.sum())
    if total <= budget:
        return [(0, n)]
    cum = torch.cumsum(count, 0).cpu()
    runs, a = [], 0
    while a < n:
        before = int(cum[a - 1]) if a > 0 else 0
        b = int(torch.searchsorted(cum, before + budget, right=True))
        b = max(b, a + 1)
        runs.append((a, b))
        a = b
    return runs
