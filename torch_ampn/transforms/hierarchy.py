"""AMGHierarchy: a PyG ``Data`` mesh -> its AMG :class:`~torch_ampn.hierarchy.HierarchicalData`."""

from __future__ import annotations

import os

import torch
from torch import Tensor
from torch_geometric.data import Data
from torch_geometric.data.datapipes import functional_transform
from torch_geometric.transforms import BaseTransform

from torch_ampn.hierarchy.amg import DOWN_EDGES, OPERATORS, build_hierarchy
from torch_ampn.hierarchy.features import edge_features
from torch_ampn.hierarchy.hierarchical_data import CONTACT, DOWN, MESH, UP, HierarchicalData, edge_type

#: Attributes of ``Data`` that become the hierarchy's structure rather than ``l0`` node attributes.
_STRUCTURE = ("edge_index", "edge_attr", "contact_edge_index", "num_nodes", "batch", "ptr")


@functional_transform("amg_hierarchy")
class AMGHierarchy(BaseTransform):
    r"""Build the AMG graph hierarchy of a mesh given as a PyG ``Data`` (pyamg's root-node aggregation).

    Functional name: :obj:`amg_hierarchy`.

    The input needs ``pos`` ``[N, D]`` and ``edge_index`` ``[2, E]`` (the mesh edges, one or both
    directions; the hierarchy is built from the symmetrised graph, see
    :func:`~torch_ampn.hierarchy.build_hierarchy`). The output is a
    :class:`~torch_ampn.hierarchy.HierarchicalData`:

    * level ``l0`` holds every node attribute of the input (``x``, ``y``, ``pos``, ``pos0``,
      ``component``, ...) and its triangles ``face`` ``[3, T]`` if any (batched like a PyG
      ``Data``'s), its mesh edges are the input's ``edge_index`` as given;
    * a coarse level ``lk`` holds the positions ``pos`` (and ``pos0``) and the ``component`` ids of
      its root fine nodes (:meth:`~torch_ampn.hierarchy.HierarchicalData.fine_index`) and ``root``;
    * with ``edge_features`` (default), every mesh, down and up edge gets the seed paper's
      relative-position features as ``edge_attr``
      (:func:`~torch_ampn.hierarchy.features.edge_features`: :math:`x_i - x_j` and its norm, ``[E, 4]``
      in 3-D, ``[E, 3]`` in 2-D; twice that with ``pos0``, the initial positions, appended). An
      input ``edge_attr`` ``[E, F]`` is appended on ``l0``'s mesh edges, and the coarse mesh
      edges get zeros in its place; without ``edge_features`` it is ``l0``'s mesh ``edge_attr``;
    * contact edges an earlier :class:`~torch_ampn.transforms.ComponentRadiusGraph` stored as
      ``contact_edge_index`` become ``l0``'s contact relation (with their relative-position
      features), and the coarse levels get none; otherwise the hierarchy has no contact
      relation. For contact edges on every level apply ``ComponentRadiusGraph`` after this
      transform, to the hierarchy;
    * graph attributes (not per node or edge) are kept.

    It is deterministic.

    Batching: it batches with PyG's ``DataLoader`` (``data["lk"].batch`` per level), but the
    meshes of one batch must have the same number of levels, and the level count depends on
    the mesh (coarsening stops at ``min_coarse_nodes``). PyG does not check it
    (:func:`~torch_ampn.hierarchy.check_level_counts` does): for a dataset of meshes of
    different sizes pass ``num_levels``, which gives every mesh exactly that many levels or
    raises ``ValueError`` for a mesh that does not coarsen so far.

    Args:
        max_levels: Levels at most, the fine one included (4 in the paper).
        min_coarse_nodes: A coarse level is kept only with at least this many nodes.
        operator: ``"adjacency"`` (``A + I``, ROBIN's) or ``"laplacian"``; see
            :func:`~torch_ampn.hierarchy.mesh_operator`.
        down_edges: ``"smoothed"`` (non-zeros of the prolongator) or ``"tentative"`` (one per node).
        edge_features: Whether to compute the relative-position ``edge_attr`` of every edge.
        cache_dir: Where to keep built hierarchies by topology (see
            :func:`~torch_ampn.hierarchy.build_hierarchy`); ``None``: no cache.
        num_levels: Exactly this many levels for every mesh (``max_levels`` is then ignored), or
            a ``ValueError`` naming the mesh size; ``None``: up to ``max_levels``, as the mesh allows.

    Example:
        >>> from torch_geometric.transforms import Delaunay, FaceToEdge
        >>> data = FaceToEdge()(Delaunay()(Data(pos=torch.rand(2000, 2), x=torch.randn(2000, 5))))
        >>> h = AMGHierarchy(max_levels=3)(data)
        >>> h.num_levels, h["l1"].pos.shape, h["l0", "mesh", "l0"].edge_attr.shape[1]
        (3, torch.Size([..., 2]), 3)
    """

    def __init__(
        self,
        max_levels: int = 4,
        min_coarse_nodes: int = 16,
        operator: str = "adjacency",
        down_edges: str = "smoothed",
        edge_features: bool = True,
        cache_dir: str | os.PathLike | None = None,
        num_levels: int | None = None,
    ) -> None:
        _check_level_count(max_levels, "max_levels")
        if num_levels is not None:
            _check_level_count(num_levels, "num_levels")
        if operator not in OPERATORS:
            raise ValueError(f"AMGHierarchy: operator must be one of {OPERATORS}, got {operator!r}")
        if down_edges not in DOWN_EDGES:
            raise ValueError(f"AMGHierarchy: down_edges must be one of {DOWN_EDGES}, got {down_edges!r}")
        self.max_levels = max_levels
        self.min_coarse_nodes = min_coarse_nodes
        self.operator = operator
        self.down_edges = down_edges
        self.edge_features = bool(edge_features)
        self.cache_dir = cache_dir
        self.num_levels = num_levels

    def forward(self, data: Data) -> HierarchicalData:
        """The hierarchy of ``data`` (see the class docs)."""
        if not isinstance(data, Data):
            raise ValueError(f"AMGHierarchy expects a torch_geometric Data, got {type(data).__name__}")
        for name in ("pos", "edge_index"):
            if getattr(data, name, None) is None:
                raise ValueError(f"AMGHierarchy: the data has no {name}")
        pos: Tensor = data.pos  # [N, D]
        if pos.dim() != 2 or not pos.is_floating_point():
            raise ValueError(f"AMGHierarchy: pos must be a float tensor [N, D], got {list(pos.shape)}")
        num_nodes = int(data.num_nodes)
        h = build_hierarchy(
            data.edge_index,
            num_nodes,
            max_levels=self.max_levels if self.num_levels is None else self.num_levels,
            min_coarse_nodes=self.min_coarse_nodes,
            operator=self.operator,
            down_edges=self.down_edges,
            cache_dir=self.cache_dir,
        )
        levels = h.num_levels
        if self.num_levels is not None and levels < self.num_levels:
            raise ValueError(
                f"AMGHierarchy(num_levels={self.num_levels}): the mesh of {num_nodes} nodes coarsens to "
                f"{levels} levels only ({h.num_nodes_per_level()} nodes; a coarse level needs "
                f"min_coarse_nodes={self.min_coarse_nodes}): lower num_levels or min_coarse_nodes"
            )
        for k in range(levels):
            del h[edge_type(CONTACT, k)]  # build_hierarchy's empty contact relations
        h[edge_type(MESH, 0)].edge_index = data.edge_index  # the user's graph, as given

        # node attributes land on l0, graph attributes on the hierarchy
        fine = h["l0"]
        for key, value in data.items():
            if key in _STRUCTURE:
                continue
            if isinstance(value, Tensor) and (data.is_node_attr(key) or key == "face"):
                fine[key] = value  # node attributes, and the triangles [3, T] of a mesh
            elif not data.is_edge_attr(key):
                h[key] = value
        pos0 = data.pos0 if "pos0" in data else None
        component = fine.component if "component" in fine else None  # a node attribute [N]
        positions = [pos]
        initial = [pos0]
        for k in range(1, levels):
            idx = h.fine_index(k)
            positions.append(pos[idx])
            initial.append(None if pos0 is None else pos0[idx])
            h[f"l{k}"].pos = positions[-1]
            if pos0 is not None:
                h[f"l{k}"].pos0 = initial[-1]
            if component is not None:
                h[f"l{k}"].component = component[idx]

        if "contact_edge_index" in data:
            h[edge_type(CONTACT, 0)].edge_index = data.contact_edge_index
            if self.edge_features:
                h[edge_type(CONTACT, 0)].edge_attr = edge_features(data.contact_edge_index, pos, pos)

        given = data.edge_attr if "edge_attr" in data and data.edge_attr is not None else None
        if given is not None and given.dim() == 1:
            given = given.unsqueeze(-1)
        if not self.edge_features:
            if given is not None:
                h[edge_type(MESH, 0)].edge_attr = given
            return h
        for k in range(levels):
            store = h[edge_type(MESH, k)]
            attr = edge_features(store.edge_index, positions[k], positions[k], initial[k], initial[k])
            if given is not None:
                extra = given if k == 0 else given.new_zeros(attr.size(0), given.size(1))
                attr = torch.cat([attr, extra.to(attr.dtype)], dim=-1)
            store.edge_attr = attr
            if k + 1 < levels:
                for rel, src, dst in ((DOWN, k, k + 1), (UP, k + 1, k)):
                    store = h[edge_type(rel, k)]
                    store.edge_attr = edge_features(
                        store.edge_index, positions[src], positions[dst], initial[src], initial[dst]
                    )
        return h

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}(max_levels={self.max_levels}, "
            f"min_coarse_nodes={self.min_coarse_nodes}, operator={self.operator!r}, "
            f"down_edges={self.down_edges!r}, edge_features={self.edge_features}, "
            f"num_levels={self.num_levels})"
        )


def _check_level_count(value: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"AMGHierarchy: {name} must be an int >= 1, got {value!r}")
