r"""Contact candidates kept between steps, for a fast, static-shape rollout.

Two ways to fix the candidates of every (node, other component) query:

* ``"dense"``: every node of that component (in the node's graph). Never searched again;
  costs ``N * (C - 1) * P`` distances per step (``P``: largest component), so it suits small
  meshes (the coarse default: 1,670 nodes, 2.4 M distances).
* ``"patches"``: the nodes of every component cut once into small spatial patches (cells of
  edge ``r`` at the first call); every step bounds each patch by a sphere around its current
  centre and takes as candidates the members of the patches whose sphere reaches within ``r``
  of the node (at most ``P`` per other component, ``P`` fixed at the first call with a
  margin). Exact by the triangle inequality whatever the motion; cut again only when a node
  reaches more than ``P`` patches of a component. Static shapes for large meshes, meant for
  GPUs: on a 2-core CPU its gathers made it slower than the search (13-28 ms against 9.6 ms
  for the coarse default mesh's finest level, ``benchmarks/README.md``).
* ``"verlet"``: a Verlet list, described below.

A rollout moves nodes by a small amount per step, so the contact neighbours of a node change
slowly. :class:`ContactCandidates` searches once with a larger radius :math:`r + s` (the
*skin* :math:`s`) and keeps, per node and other component, the ``M`` (``capacity``) nearest
nodes as candidates. Every step then selects the ``k`` nearest of the candidates within
:math:`r`: a gather, a distance and ``k`` minima over ``[N, C - 1, M]``, with static shapes
(it runs under ``torch.compile``), instead of a search with data-dependent sizes.

**Exact, or rebuilt.** The selection equals :func:`~torch_ampn.transforms.component_radius_table`
(same float64 distances, ties by the smaller index) whenever no node outside a candidate list
can have come closer than the ``k``-th selected one. With :math:`\Delta_i` a node's
displacement since the search and :math:`v_g` a reference displacement of each group ``g``
(graph and component; its mean), the triangle inequality bounds the distance of any pair
``(i, j)``, ``j`` in group ``g``, from below by
:math:`d^0_{ij} - |\Delta_i - v_g| - \max_{j' \in g} |\Delta_{j'} - v_g|`. A node outside the
list of ``(i, g)`` had :math:`d^0 \ge b_{ig}`: the ``M``-th candidate's distance when the list
is full, :math:`r + s` otherwise. :meth:`ContactCandidates.select` checks
:math:`s_{ig} < b_{ig} - |\Delta_i - v_g| - \max_{j'} |\Delta_{j'} - v_g|` for every
``(i, g)`` whose bound moved at all, with :math:`s_{ig}` the ``k``-th selected distance (or
:math:`r` when fewer than ``k`` lie within :math:`r`), and returns the verdict as a tensor;
:meth:`ContactCandidates.__call__` searches again from the current positions when it fails.
A whole component moving rigidly (a tool on its path) costs nothing, since only motion
relative to its group's mean counts.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torch_ampn.transforms._checks import (
    check_backend,
    check_count,
    check_positions,
    check_radius,
    prepare_batch,
    prepare_components,
)
from torch_ampn.transforms._native import native_table
from torch_ampn.transforms._table import query_component
from torch_ampn.transforms.radius import component_radius_table

#: ``mode`` values of :class:`ContactCandidates`.
MODES = ("auto", "dense", "patches", "verlet", "search")


class CandidateState(NamedTuple):
    """Tensors of a candidate search (all on the positions' device).

    ``N`` nodes, ``C`` components, ``M`` candidates per (node, other component), ``G`` groups.
    """

    #: ``LongTensor[N, C - 1, M]`` candidate source nodes, by increasing index (unused: the row's node).
    candidates: Tensor
    #: ``BoolTensor[N, C - 1, M]`` used candidate slots.
    valid: Tensor
    #: ``DoubleTensor[N, C - 1]`` lower bound of the distance, at the search, of any node outside the list.
    bound: Tensor
    #: ``DoubleTensor[N, 3]`` positions at the search.
    pos: Tensor
    #: ``LongTensor[N]`` group (graph * C + component) of every node.
    group: Tensor
    #: ``LongTensor[N, C - 1]`` group of every (node, other component) query.
    query_group: Tensor


class DenseState(NamedTuple):
    """Every node of every (graph, component) group: the dense candidates (``G = B * C`` groups)."""

    #: ``LongTensor[G, P]`` members of every group by increasing index (padding: 0).
    members: Tensor
    #: ``BoolTensor[G, P]`` used member slots.
    valid: Tensor
    #: ``LongTensor[N]`` graph of every node.
    batch: Tensor
    #: ``LongTensor[N, C - 1]`` component of every (node, other component) query.
    query_component: Tensor
    #: ``C``.
    num_components: int


def select_dense(pos: Tensor, state: DenseState, r: float, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`select_candidates` for the dense candidates: always exact.

    The distances of every node to every member of every component of its graph,
    ``[N, C, P]``, are a broadcast over contiguous member positions (no per-pair gather),
    which ``torch.compile`` fuses with the ``k`` minima into single passes.
    """
    n = pos.size(0)
    p = pos.double()  # [N, 3]
    width, num_comp = state.members.size(1), state.num_components
    valid = state.valid.view(-1, num_comp, width)[state.batch]  # [N, C, P]
    # coordinate by coordinate: every term is contiguous in the members (vectorised when compiled)
    d2 = None
    for axis in p.unbind(dim=1):  # [N] each
        member = axis[state.members].view(-1, num_comp, width)[state.batch]  # [N, C, P]
        term = (member - axis[:, None, None]).square()
        d2 = term if d2 is None else d2 + term
    d2 = torch.where(valid, d2, math.inf)  # [N, C, P]
    slots = torch.arange(width, device=pos.device)
    picked, picked_d2 = [], []
    for j in range(k):  # the first minimum is the smallest index (members sorted)
        best = d2.argmin(dim=-1, keepdim=True)  # [N, C, 1]
        picked.append(best)
        picked_d2.append(d2.gather(-1, best))
        if j + 1 < k:
            d2 = torch.where(slots == best, math.inf, d2)
    slot_k = torch.cat(picked, dim=-1)  # [N, C, k]
    d2_k = torch.cat(picked_d2, dim=-1)
    other = state.query_component[:, :, None].expand(-1, -1, k)  # [N, C-1, k]
    slot_k, d2_k = slot_k.gather(1, other), d2_k.gather(1, other)
    group = state.batch[:, None, None] * num_comp + other  # [N, C-1, k]
    mask = d2_k <= r * r
    rows = torch.arange(n, device=pos.device)[:, None, None]
    nbr = torch.where(mask, state.members[group, slot_k], rows)
    return nbr.reshape(n, -1), mask.reshape(n, -1), torch.ones((), dtype=torch.bool, device=pos.device)


class PatchState(NamedTuple):
    """Fixed spatial patches of every group (``mode="patches"``): ``Q`` patches of at most ``M`` nodes.

    ``G`` groups of at most ``R`` patches; every (node, other component) query keeps ``P`` of
    its group's patches.
    """

    #: ``LongTensor[Q, M]`` members of every patch by increasing index (padding: 0).
    members: Tensor
    #: ``BoolTensor[Q, M]`` used member slots.
    valid: Tensor
    #: ``LongTensor[G, R]`` patches of every group (padding: 0).
    group_patches: Tensor
    #: ``BoolTensor[G, R]`` used patch slots.
    group_valid: Tensor
    #: ``LongTensor[N, C - 1]`` group of every (node, other component) query.
    query_group: Tensor
    #: ``P``: patches kept per query.
    capacity: int


def _patch_hits(p: Tensor, state: PatchState, r: float) -> tuple[Tensor, Tensor]:
    """Patches of every query's group (``[N, C - 1, R]``) and which of them may hold a node within ``r``.

    A patch may, when its bounding sphere (centre: mean of its members, radius: the farthest
    member, both at ``p``) reaches within ``r`` of the node: a member ``j`` with
    ``|x_i - x_j| <= r`` has ``|x_i - c| <= r + |x_j - c|``. The radius is rounded up so that
    floating-point error can only add patches, never drop one.
    """
    axes = p.unbind(dim=1)  # 3 x [N]
    count = state.valid.sum(dim=1).clamp_min(1).to(p.dtype)  # [Q]
    centre = [torch.where(state.valid, a[state.members], 0.0).sum(dim=1) / count for a in axes]  # 3 x [Q]
    spread = None
    for a, c in zip(axes, centre, strict=True):
        term = (a[state.members] - c[:, None]).square()
        spread = term if spread is None else spread + term  # [Q, M]
    radius = torch.where(state.valid, spread, 0.0).amax(dim=1).sqrt() * (1 + 1e-9) + 1e-9  # [Q]
    patches = state.group_patches[state.query_group]  # [N, C-1, R]
    d2 = None
    for a, c in zip(axes, centre, strict=True):
        term = (c[patches] - a[:, None, None]).square()
        d2 = term if d2 is None else d2 + term
    reach = r + radius[patches]  # [N, C-1, R]
    hit = state.group_valid[state.query_group] & (d2 <= reach * reach)
    return patches, hit


def select_patches(pos: Tensor, state: PatchState, r: float, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`select_candidates` for patch candidates: exact unless a query reaches more than ``P`` patches.

    Pure tensor code with static shapes; the ``k`` nearest are taken by the smallest distance,
    ties by the smaller node index (as :func:`~torch_ampn.transforms.component_radius_table`).
    """
    n = pos.size(0)
    p = pos.double()
    patches, hit = _patch_hits(p, state, r)  # [N, C-1, R] x2
    width = patches.size(-1)
    slots = torch.arange(width, device=pos.device)
    keep = torch.topk(torch.where(hit, slots, width + slots), state.capacity, dim=-1, largest=False)
    kept = keep.indices  # [N, C-1, P]: the hit patches first
    chosen, chosen_hit = patches.gather(-1, kept), hit.gather(-1, kept)
    exact = (hit.sum(dim=-1) <= state.capacity).all()
    cand = state.members[chosen]  # [N, C-1, P, M]
    valid = chosen_hit[..., None] & state.valid[chosen]
    cand, valid = cand.flatten(-2), valid.flatten(-2)  # [N, C-1, P M]
    d2 = None
    for a in p.unbind(dim=1):
        term = (a[cand] - a[:, None, None]).square()
        d2 = term if d2 is None else d2 + term
    d2 = torch.where(valid, d2, math.inf)
    picked, picked_d2 = [], []
    for j in range(k):  # the smallest distance, then the smallest index among equals
        best = d2.amin(dim=-1, keepdim=True)  # [N, C-1, 1]
        pick = torch.where(d2 == best, cand, n).amin(dim=-1, keepdim=True)
        picked.append(pick)
        picked_d2.append(best)
        if j + 1 < k:
            d2 = torch.where(cand == pick, math.inf, d2)
    d2_k = torch.cat(picked_d2, dim=-1)  # [N, C-1, k]
    mask = d2_k <= r * r
    rows = torch.arange(n, device=pos.device)[:, None, None]
    nbr = torch.where(mask, torch.cat(picked, dim=-1), rows)
    return nbr.reshape(n, -1), mask.reshape(n, -1), exact


class TableState(NamedTuple):
    """A table searched at the current positions (``mode="search"``)."""

    nbr: Tensor
    mask: Tensor


def select_table(
    pos: Tensor,
    state: CandidateState | DenseState | PatchState | TableState,
    r: float,
    k: int,
    num_groups: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`select_dense`, :func:`select_patches` or :func:`select_candidates`, by the kind of ``state``."""
    if isinstance(state, TableState):  # searched for these positions
        return state.nbr, state.mask, torch.ones((), dtype=torch.bool, device=pos.device)
    if isinstance(state, DenseState):
        return select_dense(pos, state, r, k)
    if isinstance(state, PatchState):
        return select_patches(pos, state, r, k)
    return select_candidates(pos, state, r, k, num_groups)


def select_candidates(
    pos: Tensor, state: CandidateState, r: float, k: int, num_groups: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The ``k`` nearest candidates within ``r`` per (node, other component), and whether that is exact.

    Pure tensor code with static shapes (``torch.compile``-friendly).

    Args:
        pos: Current positions ``[N, 3]``.
        state: The search (:meth:`ContactCandidates.build`).
        r: Contact radius.
        k: Neighbours per other component.
        num_groups: ``G`` (graphs times components).

    Returns:
        ``(nbr, mask, exact)``: the table of
        :func:`~torch_ampn.transforms.component_radius_table`, ``[N, k * (C - 1)]`` each, and a
        ``BoolTensor[]`` that is ``True`` when the table is guaranteed to equal it.
    """
    n = pos.size(0)
    p = pos.double()  # [N, 3]
    cand = state.candidates  # [N, C-1, M]
    d = p[cand] - p[:, None, None, :]  # [N, C-1, M, 3]
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    d2 = torch.where(state.valid, d2, math.inf)
    picked, picked_d2 = [], []
    for j in range(k):  # k passes of argmin: the first minimum is the smallest index (candidates sorted)
        best = d2.argmin(dim=-1, keepdim=True)  # [N, C-1, 1]
        picked.append(cand.gather(-1, best))
        picked_d2.append(d2.gather(-1, best))
        if j + 1 < k:
            d2 = d2.scatter(-1, best, math.inf)
    d2_k = torch.cat(picked_d2, dim=-1)  # [N, C-1, k]
    mask = d2_k <= r * r
    rows = torch.arange(n, device=pos.device)[:, None, None]
    nbr = torch.where(mask, torch.cat(picked, dim=-1), rows)
    # the check: k-th selected distance (or r) below the bound minus the relative motion
    found_k = mask[..., -1]  # [N, C-1]
    s = torch.where(found_k, d2_k[..., -1].clamp_min(0).sqrt(), r)
    moved = p - state.pos  # [N, 3]
    counts = torch.zeros(num_groups, dtype=p.dtype, device=p.device).index_add_(
        0, state.group, torch.ones_like(p[:, 0])
    )
    mean = torch.zeros(num_groups, 3, dtype=p.dtype, device=p.device).index_add_(0, state.group, moved)
    mean = mean / counts.clamp_min(1)[:, None]  # [G, 3]
    spread = torch.zeros(num_groups, dtype=p.dtype, device=p.device).scatter_reduce(
        0, state.group, (moved - mean[state.group]).norm(dim=-1), "amax", include_self=True
    )  # [G]
    own = (moved[:, None, :] - mean[state.query_group]).norm(dim=-1)  # [N, C-1]
    slack = own + spread[state.query_group]  # [N, C-1]
    exact = ((s < state.bound - slack) | (slack == 0)).all()
    return nbr.reshape(n, -1), mask.reshape(n, -1), exact


class ContactCandidates:
    r"""Candidates of :func:`~torch_ampn.transforms.component_radius_table` kept between steps.

    Call it with the current positions for the table of the ``k`` nearest nodes of every other
    component within ``r``, the same as ``component_radius_table(pos, component, r, k)``; it
    searches again (with radius ``r + skin`` and ``capacity`` candidates) only when the check
    of :func:`select_candidates` cannot guarantee that (see the module docs).

    Args:
        component: ``LongTensor[N]`` component of every node (fixed for the object's life).
        r: Contact radius (inclusive).
        k: Neighbours per other component.
        num_components: ``C`` (table width ``k * (C - 1)``); default ``component.max() + 1``.
        batch: ``LongTensor[N]`` graph of every node (nodes of different graphs are never linked).
        skin: Extra search radius :math:`s`; default ``r``. Larger: fewer searches, more candidates.
        capacity: Candidates ``M >= k`` per (node, other component); default ``2 k + 2``.
        backend: Search backend (see :func:`~torch_ampn.transforms.component_radius_table`).
        mode: ``"dense"``, ``"patches"``, ``"verlet"``, ``"search"`` (no candidates: a plain
            search at every call) or ``"auto"`` (dense up to :attr:`DENSE_LIMIT` distances per step, else
            search: on the coarse default mesh the Verlet check fails too often to pay, see
            ``benchmarks/README.md``).

    Attributes:
        searches: How many searches ran (the first included).
        state: The last search's :class:`CandidateState` (``None`` before the first call).
    """

    #: Largest ``N * (C - 1) * P`` for which ``mode="auto"`` takes the dense candidates.
    DENSE_LIMIT = 1 << 18

    def __init__(
        self,
        component: Tensor,
        r: float,
        k: int,
        num_components: int | None = None,
        batch: Tensor | None = None,
        skin: float | None = None,
        capacity: int | None = None,
        backend: str = "auto",
        mode: str = "auto",
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.r = check_radius(r)
        self.k = check_count(k, "k")
        self.skin = self.r if skin is None else float(skin)
        if not (math.isfinite(self.skin) and self.skin >= 0):
            raise ValueError(f"skin must be a finite number >= 0, got {skin!r}")
        self.capacity = 2 * self.k + 2 if capacity is None else check_count(capacity, "capacity")
        if self.capacity < self.k:
            raise ValueError(f"capacity must be >= k = {self.k}, got {self.capacity}")
        dummy = torch.zeros(component.size(0), 3, device=component.device)
        self.component, self.num_components = prepare_components(component, dummy, num_components)
        self.batch, self.num_graphs = prepare_batch(batch, dummy)
        self.backend = backend
        # the C search, called directly with the checked components (no per-step checks but the positions')
        self._native = check_backend(backend, component.device) == "native"
        self.num_groups = self.num_graphs * self.num_components
        group = self.batch * self.num_components + self.component
        largest = int(torch.bincount(group, minlength=self.num_groups).max()) if group.numel() else 0
        if mode == "auto":
            work = group.numel() * (self.num_components - 1) * largest
            mode = "dense" if work <= self.DENSE_LIMIT else "search"
        self.mode = mode
        self.searches = 0
        self.state: CandidateState | None = None

    def build(self, pos: Tensor) -> CandidateState | DenseState:
        """Search the candidates around ``pos`` ``[N, 3]`` (eager; data-dependent sizes)."""
        n, c = pos.size(0), self.num_components
        if self.mode == "search":
            self.state = TableState(*self._search(pos, self.r, self.k))
            self.searches += 1
            return self.state
        slot = torch.arange(c - 1, device=pos.device)
        query_group = self.batch[:, None] * c + query_component(slot[None, :], self.component[:, None])
        group = self.batch * c + self.component
        p = pos.double()
        if self.mode == "dense":
            if self.state is None:
                members, used = _group_members(group, self.num_groups)
                self.state = DenseState(
                    members, used, self.batch, query_component(slot[None, :], self.component[:, None]), c
                )
                self.searches += 1
            return self.state
        if self.mode == "patches":  # first call, or a query reached more than P patches
            self.state = _build_patches(p, group, query_group, self.num_groups, self.r)
            self.searches += 1
            return self.state
        m, reach = self.capacity, self.r + self.skin
        nbr, mask = self._search(pos, reach, m)
        nbr, mask = nbr.view(n, c - 1, m), mask.view(n, c - 1, m)
        d = p[nbr] - p[:, None, None, :]
        d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
        full = mask.all(dim=-1)  # [N, C-1]
        bound = torch.where(full, torch.where(mask, d2, 0.0).amax(dim=-1).sqrt(), reach)
        order = torch.where(mask, nbr, n + torch.arange(m, device=pos.device)).argsort(dim=-1)
        nbr, mask = nbr.gather(-1, order), mask.gather(-1, order)
        self.state = CandidateState(
            candidates=nbr,
            valid=mask,
            bound=bound,
            pos=p.clone(),
            group=group,
            query_group=query_group,
        )
        self.searches += 1
        return self.state

    def _search(self, pos: Tensor, r: float, k: int) -> tuple[Tensor, Tensor]:
        """:func:`~torch_ampn.transforms.component_radius_table` of this object's components."""
        if self._native and pos.device.type == "cpu":
            check_positions(pos)
            return native_table(pos, self.component, self.batch, self.num_graphs, r, k, self.num_components)
        c = self.num_components
        return component_radius_table(
            pos, self.component, r, k, num_components=c, batch=self.batch, backend=self.backend
        )

    def select(self, pos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """:func:`select_candidates` on the current state (no search)."""
        if self.state is None:
            raise RuntimeError("ContactCandidates.select before the first search: call it or build() first")
        return select_table(pos, self.state, self.r, self.k, self.num_groups)

    def __call__(self, pos: Tensor) -> tuple[Tensor, Tensor]:
        """``(nbr, mask)`` of ``component_radius_table`` at ``pos``, searching again only when needed."""
        if self.state is None or self.mode == "search":
            self.build(pos)
        nbr, mask, exact = self.select(pos)
        if not bool(exact):
            self.build(pos)
            nbr, mask, _ = self.select(pos)
        return nbr, mask


def _group_members(group: Tensor, num_groups: int) -> tuple[Tensor, Tensor]:
    """Members of every group by increasing index, ``[G, P]``, and which slots are used."""
    n = group.numel()
    order = torch.argsort(group * n + torch.arange(n, device=group.device))  # by group, then index
    counts = torch.bincount(group, minlength=num_groups)  # [G]
    width = max(int(counts.max()) if n else 0, 1)
    start = torch.cumsum(counts, 0) - counts  # [G]
    rank = torch.arange(n, device=group.device) - start[group[order]]
    members = torch.zeros(num_groups, width, dtype=torch.long, device=group.device)
    members[group[order], rank] = order
    used = torch.arange(width, device=group.device)[None, :] < counts[:, None]  # [G, P]
    return members, used


def _build_patches(p: Tensor, group: Tensor, query_group: Tensor, num_groups: int, r: float) -> PatchState:
    """Cut every group into cells of edge ``r`` at ``p`` (float64) and fix ``P`` with a margin."""
    cell = torch.floor((p - p.min(dim=0).values) / r).long()  # [N, 3]
    key = torch.cat([group[:, None], cell], dim=1)  # [N, 4]
    _, patch = torch.unique(key, dim=0, return_inverse=True)  # [N] patch of every node
    num_patches = int(patch.max()) + 1 if patch.numel() else 1
    members, valid = _group_members(patch, num_patches)  # [Q, M]
    patch_group = torch.zeros(num_patches, dtype=torch.long, device=p.device).scatter_(0, patch, group)
    group_patches, group_valid = _group_members(patch_group, num_groups)  # [G, R]
    state = PatchState(members, valid, group_patches, group_valid, query_group, group_patches.size(1))
    _, hit = _patch_hits(p, state, r)
    most = int(hit.sum(dim=-1).max()) if hit.numel() else 0
    capacity = min(max(most + max(most // 2, 2), 1), group_patches.size(1))  # room for deformation
    return state._replace(capacity=capacity)
