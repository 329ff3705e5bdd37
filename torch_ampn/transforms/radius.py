r"""Contact edges between components: per other component, the k nearest nodes within a radius.

The seed paper links every node to nearby nodes of *other* components (plies, punch, die) so
that a message passing network can learn contact. For every target node :math:`i` and every
component :math:`c \neq c_i` the contact edges are

.. math::
    \{(j, i) : j \in \mathrm{kNN}_k\{ j' : c_{j'} = c,\ \|x_{j'} - x_i\| \le r \}\},

the :math:`k` nearest nodes of component :math:`c` within radius :math:`r`, ties in distance
broken by the smaller node index. Same-component pairs are never linked. With :math:`C`
components a node has at most :math:`k (C - 1)` contact edges, so the edges fit a
fixed-shape table ``[N, k * (C - 1)]`` with a validity mask (:func:`component_radius_table`),
whose shape depends only on ``N``, ``k`` and ``C``: a rollout that feeds it to a compiled
model keeps static shapes. The search itself has data-dependent sizes and runs eagerly.

"Within :math:`r`" means ``dx*dx + dy*dy + dz*dz <= r*r`` evaluated in float64 on the given
positions, whatever their precision; distances and ties are compared in that form too.

Backends (all give identical results):

* ``"grid"``: pure PyTorch, CPU or CUDA (:mod:`torch_ampn.transforms._grid_search`). Nodes
  are sorted into a cell grid per (graph, component)
  (:class:`~torch_ampn.transforms._grid.CellGrid`); each (node, other component) query reads
  the cells of a small box around its node, cut to the search ball, and selects the ``k``
  nearest by segment-wise minima. A query whose ``k``-th distance the box does not yet cover
  gets one more pass with the box that covers it (or a doubled box while fewer than ``k``
  were found). The cell edge adapts to the density
  (:func:`~torch_ampn.transforms._grid_search.auto_cell_size`). Cost grows with the number
  of nearby candidates, about linearly in ``N`` for a given mesh density; memory is bounded
  by processing candidates in chunks.
* ``"torch_cluster"``: candidate pairs from ``torch_cluster.radius`` (optional dependency;
  compiled, but it returns all neighbours of every component before selection;
  :mod:`torch_ampn.transforms._cluster`).
* ``"native"``: the same cell grid in C, CPU only, compiled with the system C compiler at
  first use (:mod:`torch_ampn.transforms._native`): one pass instead of a few hundred small
  kernels, which is what a CPU rollout on a small mesh waits for.
* ``"auto"``: ``"native"`` for positions on the CPU where a C compiler is there, else
  ``"grid"`` (``benchmarks/contact.py`` compares them).

The transform :class:`~torch_ampn.transforms.contact.ComponentRadiusGraph` applies
:func:`component_radius_table` to every level of a hierarchy.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_ampn.transforms._checks import (
    check_backend,
    check_cell_size,
    check_count,
    check_positions,
    check_radius,
    prepare_batch,
    prepare_components,
)
from torch_ampn.transforms._cluster import cluster_pairs, cluster_table
from torch_ampn.transforms._grid import CellGrid, cells_needed, squared_distance
from torch_ampn.transforms._grid_search import default_cell_size, grid_table
from torch_ampn.transforms._native import native_table


def component_radius_table(
    pos: Tensor,
    component: Tensor,
    r: float,
    k: int = 3,
    *,
    num_components: int | None = None,
    batch: Tensor | None = None,
    backend: str = "auto",
    cell_size: float | None = None,
) -> tuple[Tensor, Tensor]:
    """Contact neighbours as a fixed-shape table: per node and other component, the k nearest within r.

    Slot layout of row ``i``: the ``C - 1`` components other than ``component[i]`` in
    increasing id order, ``k`` slots each, nearest first (ties by the smaller node index).
    Unused slots hold ``i`` itself with ``mask`` False. Nodes of different graphs of a
    batch are never neighbours.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        component: ``[N]`` integer component id of every node (``>= 0``; ids without
            nodes are allowed).
        r: Search radius (inclusive), ``> 0``, in the units of ``pos`` (no default: it depends on the mesh).
        k: Neighbours per other component, ``>= 1``.
        num_components: ``C``; defaults to ``component.max() + 1``. Pass it to keep the
            table width fixed when some components may be missing.
        batch: Optional ``[N]`` graph id of every node (as in PyG's ``Batch``).
        backend: ``"auto"``, ``"grid"``, ``"native"`` or ``"torch_cluster"`` (see the module docs).
        cell_size: Cell edge of the ``"grid"`` backend (a speed knob, never changes the
            result); defaults to
            :func:`~torch_ampn.transforms._grid_search.auto_cell_size`.

    Returns:
        ``(nbr, mask)``: ``nbr`` ``LongTensor[N, k * (C - 1)]`` source node of every slot,
        ``mask`` ``BoolTensor[N, k * (C - 1)]`` which slots hold an edge.
    """
    check_positions(pos)
    r = check_radius(r)
    k = check_count(k, "k")
    check_cell_size(cell_size)
    backend = check_backend(backend, pos.device)
    comp, num_comp = prepare_components(component, pos, num_components)
    batch, num_graphs = prepare_batch(batch, pos)
    if backend == "torch_cluster":
        return cluster_table(pos, comp, batch, r, k, num_comp)
    if backend == "native":
        return native_table(pos, comp, batch, num_graphs, r, k, num_comp)
    return grid_table(pos, comp, batch, num_graphs, r, k, num_comp, cell_size)


def table_to_edge_index(nbr: Tensor, mask: Tensor) -> Tensor:
    """Edge list of a neighbour table: one edge ``(nbr[i, s], i)`` per slot with ``mask[i, s]``.

    Args:
        nbr: ``LongTensor[N, S]`` source node of every slot.
        mask: ``BoolTensor[N, S]`` valid slots.

    Returns:
        ``LongTensor[2, M]`` rows (source, target), in row-major slot order: sorted by target,
        then by slot (for :func:`component_radius_table`: other component, then distance).
    """
    if nbr.shape != mask.shape or nbr.dim() != 2:
        raise ValueError(
            f"nbr and mask must be [N, S] of equal shape, got {list(nbr.shape)} and {list(mask.shape)}"
        )
    target = torch.arange(nbr.size(0), device=nbr.device)[:, None].expand_as(nbr)
    return torch.stack([nbr[mask], target[mask]])


def component_radius_graph(
    pos: Tensor,
    component: Tensor,
    r: float,
    k: int = 3,
    *,
    num_components: int | None = None,
    batch: Tensor | None = None,
    backend: str = "auto",
    cell_size: float | None = None,
) -> Tensor:
    """Contact edges: for every node and every other component, the k nearest nodes within r.

    Edges never join nodes of the same component (nor of different graphs of a batch).
    Arguments as in :func:`component_radius_table`, whose table this flattens with
    :func:`table_to_edge_index`.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        component: ``[N]`` integer component id of every node.
        r: Search radius (inclusive), ``> 0``.
        k: Neighbours per other component, ``>= 1``.
        num_components: ``C``; defaults to ``component.max() + 1``.
        batch: Optional ``[N]`` graph id of every node.
        backend: ``"auto"``, ``"grid"`` or ``"torch_cluster"``.
        cell_size: Cell edge of the ``"grid"`` backend (speed only).

    Returns:
        ``LongTensor[2, M]``, rows (source ``j``, target ``i``), ``M <= N * k * (C - 1)``;
        sorted by target, then by the source's component, then by (distance, index).
    """
    nbr, mask = component_radius_table(
        pos, component, r, k, num_components=num_components, batch=batch, backend=backend, cell_size=cell_size
    )
    return table_to_edge_index(nbr, mask)


def plain_radius_graph(
    pos: Tensor,
    r: float,
    *,
    batch: Tensor | None = None,
    loop: bool = False,
    backend: str = "auto",
    cell_size: float | None = None,
) -> Tensor:
    """All pairs of nodes within ``r``, whatever their component (the plain radius graph).

    Kept to compare edge counts with :func:`component_radius_graph`; exact, no neighbour limit.

    Args:
        pos: ``[N, 3]`` floating point node positions.
        r: Search radius (inclusive), ``> 0``.
        batch: Optional ``[N]`` graph id of every node; graphs are never joined.
        loop: Keep self-loops ``(i, i)``.
        backend: ``"auto"``, ``"grid"`` or ``"torch_cluster"``.
        cell_size: Cell edge of the ``"grid"`` backend (speed only); defaults to ``r``.

    Returns:
        ``LongTensor[2, E]`` rows (source ``j``, target ``i``), sorted by target, then source.
    """
    check_positions(pos)
    r = check_radius(r)
    check_cell_size(cell_size)
    if backend == "native":
        raise ValueError("plain_radius_graph: backend='native' is not implemented; use 'grid' or 'auto'")
    backend = check_backend(backend)
    batch, num_graphs = prepare_batch(batch, pos)
    n = pos.size(0)
    if n == 0:
        return torch.empty(2, 0, dtype=torch.long, device=pos.device)
    pos64 = pos.to(torch.float64)
    if backend == "torch_cluster":
        source, target = cluster_pairs(pos, r, batch)
        keep = squared_distance(pos64, source, target) <= r * r
        if not loop:
            keep &= source != target
        return _sorted_edges(source[keep], target[keep], n)
    grid = CellGrid(pos64, batch, num_graphs, cell_size or default_cell_size(r), r)
    node = torch.arange(n, device=pos.device)
    bound2 = torch.full((n,), r * r, dtype=torch.float64, device=pos.device)
    parts = [
        _sorted_edges(chunk.source, node[chunk.start : chunk.stop][chunk.query], n)
        for chunk in grid.candidates(
            node, batch, cells_needed(r, grid.cell_size), bound2, exclude_self=not loop
        )
    ]
    return torch.cat(parts, 1) if parts else torch.empty(2, 0, dtype=torch.long, device=pos.device)


def _sorted_edges(source: Tensor, target: Tensor, n: int) -> Tensor:
    order = torch.argsort(target * n + source)
    return torch.stack([source[order], target[order]])
