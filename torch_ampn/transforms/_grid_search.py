"""The ``"grid"`` backend of the contact-edge search: per-query box passes over a :class:`CellGrid`.

Nodes are sorted into a cell grid per (graph, component)
(:class:`~torch_ampn.transforms._grid.CellGrid`); each (node, other component) query reads
the cells of a small box around its node, cut to the search ball, and selects the ``k``
nearest by segment-wise minima (:func:`~torch_ampn.transforms._select.segment_topk`). A
query whose ``k``-th distance the box does not yet cover gets one more pass with the box
that covers it (or a doubled box while fewer than ``k`` were found). The cell edge adapts
to the density (:func:`auto_cell_size`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torch_ampn.transforms._grid import EPS_CELLS, CellGrid, cells_needed, coverage
from torch_ampn.transforms._select import segment_topk
from torch_ampn.transforms._table import empty_table, fill_table, query_component

#: Boxes of at most this many cells (per side) are searched whole in the first pass.
START_FULL_BOX = 2


def default_cell_size(r: float) -> float:
    """Cell edge of one cell per radius.

    Just over ``r``, so that the box of one cell around a node covers its ball (see
    :func:`~torch_ampn.transforms._grid.coverage`).
    """
    return r / (1.0 - 4 * EPS_CELLS)


def auto_cell_size(pos: Tensor, group: Tensor, r: float) -> float:
    """Cell edge for the grid backend, from how densely the groups fill cells of edge ``r``.

    Sparse point sets (at most about one node of a group per ``r``-cell, as the paper's mesh
    at ``r = 3`` mm) get one cell per radius and are searched in one pass. Denser ones get
    ``r / m`` so that a cell holds about one node of a group, ``m = (occupancy / 1.2)**(1/d)``
    (``1 <= m <= 8``) with the local dimension ``d`` (2 for shells, 3 for volumes) read off
    the occupancies at edges ``r`` and ``r / 2``. Affects speed only, never the result.

    Args:
        pos: ``[N, 3]`` float64 positions.
        group: ``[N]`` long group (graph x component) of every node.
        r: Search radius.
    """
    h = default_cell_size(r)
    occupancy = _occupancy(pos, group, h)
    if occupancy <= 1.5:
        return h
    dim = min(max(math.log2(max(occupancy / _occupancy(pos, group, h / 2), 1.0)), 1.0), 3.0)
    m = min(max(round((occupancy / 1.2) ** (1.0 / dim)), 1), 8)
    return r / (m - 4 * EPS_CELLS)


def _occupancy(pos: Tensor, group: Tensor, h: float) -> float:
    """Mean number of nodes per occupied (group, cell) for cells of edge ``h``.

    Estimated by hashing cells into ``~4 N`` bins; collisions only lower the count of
    occupied cells.
    """
    cell = torch.floor((pos - pos.min(0).values) / h).long()
    key = (group * 73856093) ^ (cell[:, 0] * 19349663) ^ (cell[:, 1] * 83492791) ^ (cell[:, 2] * 50331653)
    bins = 4 * pos.size(0) + 1
    occupied = int(torch.count_nonzero(torch.bincount(key % bins, minlength=bins)))  # % is >= 0
    return pos.size(0) / max(occupied, 1)


def _grid_select(
    grid: CellGrid, node: Tensor, group: Tensor, rho: int, bound2: Tensor, k: int
) -> tuple[Tensor, Tensor]:
    """Top-``k`` (distance, index) nodes of ``group[q]`` within ``sqrt(bound2[q])`` of ``node[q]``.

    Searches the box of ``+-rho`` cells; returns ``[Q, k]`` indices (``-1``: none) and
    squared distances.
    """
    parts_i, parts_d = [], []
    for chunk in grid.candidates(node, group, rho, bound2):
        idx, d2 = segment_topk(chunk.query, chunk.dist2, chunk.source, chunk.stop - chunk.start, k)
        parts_i.append(idx)
        parts_d.append(d2)
    if not parts_i:
        return segment_topk(node.new_empty(0), bound2.new_empty(0), node.new_empty(0), 0, k)
    return torch.cat(parts_i), torch.cat(parts_d)


def _next_box(
    rho: int, found: Tensor, kth_d2: Tensor, floor2: Tensor, last: Tensor, r: float, h: float
) -> tuple[Tensor, Tensor]:
    """Box half-width and squared bound of the next pass of queries not yet resolved.

    With ``k`` found, the ``k``-th distance bounds the answer: the box that covers it settles
    the query in one more pass. With fewer found the box doubles, up to ``last``.
    """
    full = found & (kth_d2 <= r * r)
    exact = _cells_for(kth_d2 - floor2, h)
    rho_next = torch.where(full, exact, 2 * rho).clamp(min=rho + 1)
    rho_next = torch.minimum(rho_next, last)
    bound2 = torch.where(full, kth_d2, torch.full_like(kth_d2, r * r))
    return rho_next, bound2


def _take(tensors: tuple[Tensor, ...], index: Tensor) -> tuple[Tensor, ...]:
    """``t.index_select(0, index)`` of every tensor (one host sync for all, not one each)."""
    return tuple(t.index_select(0, index) for t in tensors)


def _cells_for(reach2: Tensor, h: float) -> Tensor:
    """Smallest box half-width (cells) whose coverage reaches ``sqrt(reach2)``, at least 1."""
    return torch.ceil(torch.sqrt(reach2.clamp(min=0.0)) / h + EPS_CELLS).long().clamp(min=1)


def grid_table(
    pos: Tensor,
    comp: Tensor,
    batch: Tensor,
    num_graphs: int,
    r: float,
    k: int,
    num_comp: int,
    cell_size: float | None,
) -> tuple[Tensor, Tensor]:
    """The contact table ``(nbr, mask)``, both ``[N, k * (C - 1)]``, searched on a cell grid.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        comp: ``[N]`` long component id of every node.
        batch: ``[N]`` long graph id of every node.
        num_graphs: Number of graphs in ``batch``.
        r: Search radius.
        k: Neighbours per other component.
        num_comp: Number of components ``C``.
        cell_size: Cell edge; ``None`` for :func:`auto_cell_size`.
    """
    n, num_other = pos.size(0), num_comp - 1
    nbr, mask = empty_table(n, k * num_other, pos.device)
    if n == 0 or num_other == 0:
        return nbr, mask
    pos64 = pos.to(torch.float64)
    node_group = batch * num_comp + comp
    grid = CellGrid(
        pos64, node_group, num_graphs * num_comp, cell_size or auto_cell_size(pos64, node_group, r), r
    )
    queries = _Queries(comp, batch, num_comp, node_group, grid)
    state = queries.initial_state(r)
    while state[0].numel():
        parts = []
        values = torch.unique(state[1]).tolist()
        for value in values:
            pick = state if len(values) == 1 else _take(state, (state[1] == value).nonzero().squeeze(1))
            parts.append(_search_pass(grid, queries, pick, value, r, k, nbr, mask))
        state = tuple(torch.cat(t) for t in zip(*parts, strict=True))
    return nbr, mask


class _Queries:
    """The (target node, other component) queries ``q = i * (C - 1) + slot`` of the table."""

    def __init__(
        self, comp: Tensor, batch: Tensor, num_comp: int, node_group: Tensor, grid: CellGrid
    ) -> None:
        self.num_other = num_comp - 1
        self.grid = grid
        query = torch.arange(comp.numel() * self.num_other, device=comp.device)
        self.target = torch.div(query, self.num_other, rounding_mode="floor")
        slot_comp = query_component(query % self.num_other, comp.index_select(0, self.target))
        self.group = batch.index_select(0, self.target) * num_comp + slot_comp  # group searched
        self.group_size = torch.bincount(node_group, minlength=grid.num_groups)

    def initial_state(self, r: float) -> tuple[Tensor, ...]:
        """``(query, rho, bound2, floor2, last)`` of the queries with anything in reach.

        ``floor2`` bounds the squared distance to the group from below, ``last`` is the box
        half-width that covers the whole ball, ``rho`` the first box and ``bound2 = r**2``.
        """
        grid = self.grid
        floor2 = grid.floor2(self.target, self.group)
        reachable = (self.group_size.index_select(0, self.group) > 0) & (floor2 <= r * r)
        query = reachable.nonzero().squeeze(1)
        floor2 = floor2.index_select(0, query)
        m = cells_needed(r, grid.cell_size)
        last = _cells_for(r * r - floor2, grid.cell_size).clamp(max=m)
        rho = last if m <= START_FULL_BOX else torch.ones_like(last)  # small box: whole ball at once
        bound2 = torch.full(query.shape, r * r, dtype=torch.float64, device=query.device)
        return query, rho, bound2, floor2, last


def _search_pass(
    grid: CellGrid,
    queries: _Queries,
    state: tuple[Tensor, ...],
    rho: int,
    r: float,
    k: int,
    nbr: Tensor,
    mask: Tensor,
) -> tuple[Tensor, ...]:
    """Search the box of ``+-rho`` cells for every query of ``state``.

    Writes the queries that this settles into the table ``(nbr, mask)`` and returns the
    state of the others for the next pass.
    """
    q, _, b2, f2, end = state
    idx, d2 = _grid_select(
        grid, queries.target.index_select(0, q), queries.group.index_select(0, q), rho, b2, k
    )
    found = idx[:, -1] >= 0
    done = (found & (d2[:, -1] <= coverage(rho, grid.cell_size) ** 2 + f2)) | (rho >= end)
    finished, todo = done.nonzero().squeeze(1), (~done).nonzero().squeeze(1)
    fill_table(nbr, mask, q.index_select(0, finished), idx.index_select(0, finished), k, queries.num_other)
    q, found, kth_d2, f2, end = _take((q, found, d2[:, -1], f2, end), todo)
    rho_next, bound2 = _next_box(rho, found, kth_d2, f2, end, r, grid.cell_size)
    return q, rho_next, bound2, f2, end
