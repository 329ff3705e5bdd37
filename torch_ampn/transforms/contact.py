"""The transform that fills the contact edges of every level of a hierarchy.

The edges themselves come from :func:`~torch_ampn.transforms.radius.component_radius_table`
(see :mod:`torch_ampn.transforms.radius`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import torch
from torch import Tensor
from torch_geometric.data import Data
from torch_geometric.data.datapipes import functional_transform
from torch_geometric.transforms import BaseTransform

from torch_ampn.hierarchy.features import edge_features
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.transforms._checks import check_backend, check_count, check_radius
from torch_ampn.transforms.radius import component_radius_table, plain_radius_graph, table_to_edge_index

MODES = ("component_knn", "radius")
POSITIONS = ("current", "initial")


@functional_transform("component_radius_graph")
class ComponentRadiusGraph(BaseTransform):
    r"""Fills the contact edges ``("lk", "contact", "lk")`` on every level of a hierarchy.

    Functional name: :obj:`component_radius_graph`.

    Positions may be 3-D or 2-D (``[N, 2]``: searched in the plane). On a plain ``Data`` (``pos``
    and a ``component`` vector ``LongTensor[N]``; ``batch`` when batched) it stores the contact
    edges as ``data.contact_edge_index`` ``[2, M]`` (and, with ``static``, ``contact_nbr`` and
    ``contact_mask``: indices of one graph, which ``Batch`` does not offset), beside the mesh's
    ``edge_index``;
    :class:`~torch_ampn.transforms.AMGHierarchy` takes them on as ``l0``'s contact relation.

    For every node and every *other* component it links the ``k`` nearest nodes of that
    component within the level's radius
    (:func:`~torch_ampn.transforms.radius.component_radius_graph`). Level ``k`` uses the
    current positions and component ids of its nodes' fine roots:
    ``idx = data.fine_index(k)``, ``pos_k = data["l0"].pos[idx]``,
    ``component_k = data["l0"].component[idx]``. On a batch (``Batch.from_data_list``),
    nodes of different graphs are never linked (``data["lk"].batch``).

    Per-level radius: by default every level uses the same ``r`` (contact is a physical
    distance, and coarse nodes are fine nodes, so ``r`` keeps its meaning). With
    ``level_radius_scale`` a number ``s``, level ``k`` uses ``r * s**k`` (e.g. ``s = 2`` to
    follow the coarse mesh spacing); with a sequence, level ``k`` uses
    ``r * level_radius_scale[k]`` (it needs an entry for every level).

    Two variants for comparison with the seed paper's choice (``mode="component_knn"``,
    ``positions="current"``): ``mode="radius"`` links *all* nodes within ``r``, of any
    component (the conventional radius graph, :func:`~torch_ampn.transforms.plain_radius_graph`;
    no ``k`` limit, no static tables); ``positions="initial"`` builds the edges from the
    initial positions ``data["l0"].pos0``, so they stay the same for a whole trajectory
    (ROBIN's static contact edges).

    Args:
        r: Contact radius (inclusive) of level 0, ``> 0``, in the units of the positions (no
            default: it depends on the mesh; the forming models use about 3 mm).
        k: Neighbours per other component, ``>= 1``.
        level_radius_scale: ``None``, a positive number or a sequence of positive numbers
            (see above).
        num_components: ``C``; defaults to ``data["l0"].component.max() + 1``. Pass it to
            keep the tables' width fixed.
        static: Also store the fixed-shape tables as ``data["lk"].contact_nbr``
            (``[N_k, k * (C - 1)]``, level-``k`` node indices) and ``data["lk"].contact_mask``;
            ``Batch.from_data_list`` offsets ``contact_nbr`` like an edge index.
        backend: ``"auto"``, ``"grid"`` or ``"torch_cluster"``.
        merge_levels: Search all levels in one call when they share the radius (same result,
            fewer calls; meant for GPUs, where a search is bound by per-call overhead).
        mode: ``"component_knn"`` (default: the ``k`` nearest of every other component) or
            ``"radius"`` (every node within ``r``, any component).
        positions: ``"current"`` (default: ``data["l0"].pos``, rebuilt every step) or
            ``"initial"`` (``data["l0"].pos0``: the same edges at every step).
        edge_features: Also store the contact edges' relative-position features
            (:func:`~torch_ampn.hierarchy.features.edge_features` of the current positions) as
            their ``edge_attr`` (``contact_edge_attr`` on a plain ``Data``).
    """

    def __init__(
        self,
        r: float,
        k: int = 3,
        level_radius_scale: float | Sequence[float] | None = None,
        num_components: int | None = None,
        static: bool = False,
        backend: str = "auto",
        merge_levels: bool = False,
        mode: str = "component_knn",
        positions: str = "current",
        edge_features: bool = False,
    ) -> None:
        self.r = check_radius(r)
        self.k = check_count(k, "k")
        self.level_radius_scale = _check_level_scale(level_radius_scale)
        self.num_components = (
            None if num_components is None else check_count(num_components, "num_components")
        )
        self.static = bool(static)
        self.merge_levels = bool(merge_levels)
        self.backend = backend
        check_backend(backend)
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if positions not in POSITIONS:
            raise ValueError(f"positions must be one of {POSITIONS}, got {positions!r}")
        if mode == "radius" and backend == "native":
            raise ValueError("mode='radius' has no native search: use backend='grid' or 'auto'")
        if mode == "radius" and (self.static or self.merge_levels):
            raise ValueError("mode='radius' has no fixed-size tables: use static=False, merge_levels=False")
        self.mode = mode
        self.positions = positions
        self.edge_features = bool(edge_features)

    def level_radius(self, level: int) -> float:
        """Contact radius of ``level`` (``0`` is the finest)."""
        scale = self.level_radius_scale
        if scale is None:
            return self.r
        if isinstance(scale, float):
            return self.r * scale**level
        if level >= len(scale):
            raise ValueError(f"level_radius_scale has {len(scale)} entries, but level {level} needs one")
        return self.r * scale[level]

    def forward(self, data: HierarchicalData | Data) -> HierarchicalData | Data:
        """Fill ``data[lk, "contact", lk].edge_index`` on every level ``k`` (see the class docs).

        With ``merge_levels`` and the same radius on every level, all levels are searched in
        one call (levels kept apart like the graphs of a batch); the result is the same as
        level by level.
        """
        if isinstance(data, Data):
            return self._plain(data)
        pos, comp = _read_level0(data, "pos0" if self.positions == "initial" else "pos")
        levels = range(data.num_levels)
        inputs = []  # (pos_k, comp_k, batch_k) per level
        for level in levels:
            store = data.level(level)
            idx = None if level == 0 else data.fine_index(level)
            pos_k, comp_k = (pos, comp) if idx is None else (pos[idx], comp[idx])
            inputs.append((pos_k, comp_k, store.batch if "batch" in store else None))
        radii = [self.level_radius(level) for level in levels]
        num_comp = self.num_components
        if num_comp is None:
            num_comp = int(comp.max()) + 1 if comp.numel() else 1
        if self.mode == "radius":
            for level, ((p, _, b), radius) in enumerate(zip(inputs, radii, strict=True)):
                data.contact(level).edge_index = plain_radius_graph(p, radius, batch=b, backend=self.backend)
            return self._features(data)
        if self.merge_levels and len(set(radii)) == 1 and len(inputs) > 1:
            tables = self._merged_tables(inputs, radii[0], num_comp)
        else:
            tables = [
                component_radius_table(
                    p, c, radius, self.k, num_components=num_comp, batch=b, backend=self.backend
                )
                for (p, c, b), radius in zip(inputs, radii, strict=True)
            ]
        for level, (nbr, mask) in zip(levels, tables, strict=True):
            data.contact(level).edge_index = table_to_edge_index(nbr, mask)
            if self.static:
                data.level(level).contact_nbr = nbr
                data.level(level).contact_mask = mask
        return self._features(data)

    def _features(self, data: HierarchicalData) -> HierarchicalData:
        """With ``edge_features``: every level's contact ``edge_attr`` from its current positions."""
        if self.edge_features:
            pos = data["l0"].pos
            for level in range(data.num_levels):
                pos_k = pos if level == 0 else pos[data.fine_index(level)]
                store = data.contact(level)
                store.edge_attr = edge_features(store.edge_index, pos_k, pos_k)
        return data

    def _plain(self, data: Data) -> Data:
        """The contact edges of a plain ``Data`` (``pos``/``pos0``, ``component``, ``batch``)."""
        name = "pos0" if self.positions == "initial" else "pos"
        for field in (name, "component"):
            if getattr(data, field, None) is None:
                raise ValueError(f"ComponentRadiusGraph needs data.{field}")
        pos, comp = data[name], data.component
        if comp.dim() != 1 or comp.size(0) != pos.size(0) or comp.is_floating_point():
            raise ValueError(
                f"ComponentRadiusGraph: data.component must be a LongTensor [{pos.size(0)}], "
                f"got {comp.dtype} {list(comp.shape)}"
            )
        batch = data.batch if getattr(data, "batch", None) is not None else None
        pos = _three_d(pos)
        if self.mode == "radius":
            data.contact_edge_index = plain_radius_graph(pos, self.r, batch=batch, backend=self.backend)
        else:
            num_comp = self.num_components or (int(comp.max()) + 1 if comp.numel() else 1)
            nbr, mask = component_radius_table(
                pos, comp, self.r, self.k, num_components=num_comp, batch=batch, backend=self.backend
            )
            data.contact_edge_index = table_to_edge_index(nbr, mask)
            if self.static:
                data.contact_nbr, data.contact_mask = nbr, mask
        if self.edge_features:
            data.contact_edge_attr = edge_features(data.contact_edge_index, data.pos, data.pos)
        return data

    def _merged_tables(
        self, inputs: list[tuple[Tensor, Tensor, Tensor | None]], r: float, num_comp: int
    ) -> list[tuple[Tensor, Tensor]]:
        """One search over all levels; level ``k``'s graphs get group ids after level ``k-1``'s."""
        groups, offset = [], 0
        for p, _, b in inputs:
            graph = torch.zeros(p.size(0), dtype=torch.long, device=p.device) if b is None else b.long()
            groups.append(graph + offset)
            offset += int(graph.max()) + 1 if graph.numel() else 1
        nbr, mask = component_radius_table(
            torch.cat([p for p, _, _ in inputs]),
            torch.cat([c for _, c, _ in inputs]),
            r,
            self.k,
            num_components=num_comp,
            batch=torch.cat(groups),
            backend=self.backend,
        )
        tables, start = [], 0
        for p, _, _ in inputs:
            n = p.size(0)
            tables.append((nbr[start : start + n] - start, mask[start : start + n]))
            start += n
        return tables

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}(r={self.r}, k={self.k}, "
            f"level_radius_scale={self.level_radius_scale}, num_components={self.num_components}, "
            f"static={self.static}, backend={self.backend!r}, merge_levels={self.merge_levels}, "
            f"mode={self.mode!r}, positions={self.positions!r}, edge_features={self.edge_features})"
        )


def _check_level_scale(scale: float | Sequence[float] | None) -> float | tuple[float, ...] | None:
    if scale is None:
        return None
    single = isinstance(scale, numbers.Real) and not isinstance(scale, bool)
    try:
        values = [float(v) for v in ([scale] if single else scale)]
    except (TypeError, ValueError):
        raise ValueError(
            f"level_radius_scale must be None, a number or a sequence of numbers, got {scale!r}"
        ) from None
    if not values or any(not math.isfinite(v) or v <= 0 for v in values):
        raise ValueError(f"level_radius_scale must hold positive finite numbers, got {scale!r}")
    return values[0] if single else tuple(values)


def _read_level0(data: HierarchicalData, positions: str) -> tuple[Tensor, Tensor]:
    """Positions (field ``positions``) and component ids of the fine level, checked."""
    if not isinstance(data, HierarchicalData):
        raise ValueError(
            f"ComponentRadiusGraph expects a HierarchicalData or a Data, got {type(data).__name__}"
        )
    store = data["l0"]
    for name in (positions, "component"):
        if name not in store:
            raise ValueError(f'ComponentRadiusGraph needs data["l0"].{name}')
    return _three_d(store[positions]), store.component


def _three_d(pos: Tensor) -> Tensor:
    """2-D positions ``[N, 2]`` as 3-D ones in the plane z = 0 (the same distances); others as given."""
    if pos.dim() == 2 and pos.size(1) == 2:
        return torch.cat([pos, pos.new_zeros(pos.size(0), 1)], dim=1)
    return pos
