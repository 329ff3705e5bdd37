"""HierarchicalData: a PyG ``HeteroData`` holding an AMG graph hierarchy."""

from __future__ import annotations

import os
import re
from typing import Any

import torch
from torch import Tensor
from torch_geometric.data import Batch, HeteroData
from torch_geometric.data.storage import EdgeStorage, NodeStorage

from torch_ampn.utils.io import atomic_torch_save

_LEVEL_RE = re.compile(r"^l(\d+)$")


EdgeType = tuple[str, str, str]

# The four edge relations of a hierarchy, the names used in edge types and in per-relation modules.
MESH, CONTACT, DOWN, UP = "mesh", "contact", "down", "up"
RELATIONS = (MESH, CONTACT, DOWN, UP)


def level_name(level: int) -> str:
    """Node type name of hierarchy level ``level`` (``0`` is the finest): ``"l{level}"``."""
    return f"l{level}"


def edge_type(relation: str, level: int) -> EdgeType:
    """The edge type of ``relation`` at ``level``.

    ``("lk", "mesh", "lk")``, ``("lk", "contact", "lk")``, ``("lk", "down", "lk+1")`` (from level
    ``k`` to ``k + 1``) or ``("lk+1", "up", "lk")`` (from level ``k + 1`` to ``k``).
    """
    lk = level_name(level)
    if relation in (MESH, CONTACT):
        return (lk, relation, lk)
    if relation == DOWN:
        return (lk, DOWN, level_name(level + 1))
    if relation == UP:
        return (level_name(level + 1), UP, lk)
    raise ValueError(f"relation must be one of {RELATIONS}, got {relation!r}")


def _count_levels(data: HeteroData) -> int:
    return sum(1 for t in data.node_types if _LEVEL_RE.match(t))


def check_level_counts(data: HeteroData, num_levels: int) -> None:
    """Raise ``ValueError`` unless every graph of ``data`` has at least ``num_levels`` levels.

    ``data`` is one hierarchy or a PyG batch of them. ``Batch.from_data_list`` of hierarchies
    with different level counts raises nothing: the batch has the first graph's levels, and a
    level that some graphs lack holds only the others' nodes (``data["lk"].ptr`` counts fewer
    graphs), so a model would mix them up. This finds both cases.

    Args:
        data: A :class:`HierarchicalData` or a batch of them (``Batch.from_data_list``, ``DataLoader``).
        num_levels: Levels the model uses, ``>= 1``; more levels in ``data`` are fine.
    """
    if isinstance(num_levels, bool) or not isinstance(num_levels, int) or num_levels < 1:
        raise ValueError(f"num_levels must be an int >= 1, got {num_levels!r}")
    advice = (
        "build them with the same AMGHierarchy(max_levels=..., min_coarse_nodes=...) "
        "or pass AMGHierarchy(num_levels=...)"
    )
    present = _count_levels(data)
    if not isinstance(data, Batch):
        if present < num_levels:
            raise ValueError(f"the hierarchy has {present} levels, the model uses {num_levels}; {advice}")
        return
    if present < num_levels:  # the batch's levels are those of its first graph
        raise ValueError(
            f"a batch of hierarchies with too few levels: graph 0 has {present} levels, "
            f"the model uses {num_levels}; {advice}"
        )
    num_graphs = data.num_graphs
    for level in range(1, num_levels):
        lk = level_name(level)
        # graphs that gave this level nodes: the level's ptr [G_k + 1], else its collation slices
        slices = [data[lk].ptr] if "ptr" in data[lk] else list(data._slice_dict.get(lk, {}).values())
        graphs = slices[0].numel() - 1 if slices else num_graphs
        if graphs < num_graphs:  # the graphs without this level have exactly `level` levels
            raise ValueError(
                f"a batch of hierarchies with different level counts: {num_graphs - graphs} of its "
                f"{num_graphs} graphs have {level} levels, the model uses {num_levels}; {advice}"
            )


class HierarchicalData(HeteroData):
    r"""A graph hierarchy ``l0`` (fine mesh) .. ``lL`` (coarsest) as one heterogeneous graph.

    Node types are ``"l0" .. "lL"``; edge types per level ``k``:

    * ``("lk", "mesh", "lk")``: mesh edges of level ``k`` (both directions),
    * ``("lk", "contact", "lk")``: contact edges (filled per step by
      :class:`~torch_ampn.transforms.ComponentRadiusGraph`),
    * ``("lk", "down", "lk+1")``: fine-to-coarse edges (non-zeros of the prolongator
      :math:`P_k`, source fine node, target coarse node), ``edge_weight`` holds :math:`P_k`'s values,
    * ``("lk+1", "up", "lk")``: the same edges reversed (non-zeros of :math:`R_k = P_k^\top`).

    Level ``k >= 1`` stores ``root`` (``LongTensor[N_k]``): the level ``k-1`` node that each
    coarse node stands for (root-node aggregation), offset correctly when batched, as is
    the optional fixed-size contact table ``contact_nbr`` (indices into its own level).
    Positions, component ids and node types of coarse nodes are those of their roots
    (see :meth:`fine_index`).

    It batches with :class:`torch_geometric.data.Batch` and
    :class:`torch_geometric.loader.DataLoader` like any ``HeteroData``: edge indices are
    offset per level and ``data["lk"].batch`` assigns coarse nodes to graphs. The hierarchies
    of one batch need the same number of levels (PyG does not check it;
    :func:`check_level_counts` does).
    """

    # ---- structure -------------------------------------------------------------------
    @property
    def num_levels(self) -> int:
        """Number of levels ``L + 1`` (of the first graph of a batch: see :func:`check_level_counts`)."""
        return _count_levels(self)

    def _check_level(self, level: int, coarsest_ok: bool = True) -> int:
        n = self.num_levels
        hi = n if coarsest_ok else n - 1
        if level < 0:
            level += n
        if not 0 <= level < hi:
            raise IndexError(f"level {level} out of range for a hierarchy with {n} levels")
        return level

    def level(self, level: int) -> NodeStorage:
        """Node store of level ``level`` (negative counts from the coarsest)."""
        return self[level_name(self._check_level(level))]

    def mesh(self, level: int) -> EdgeStorage:
        """Edge store of the mesh edges of level ``level``."""
        return self[edge_type(MESH, self._check_level(level))]

    def contact(self, level: int) -> EdgeStorage:
        """Edge store of the contact edges of level ``level``."""
        return self[edge_type(CONTACT, self._check_level(level))]

    def down(self, level: int) -> EdgeStorage:
        """Edge store of the down edges from level ``level`` to ``level + 1``."""
        return self[edge_type(DOWN, self._check_level(level, coarsest_ok=False))]

    def up(self, level: int) -> EdgeStorage:
        """Edge store of the up edges from level ``level + 1`` to ``level``."""
        return self[edge_type(UP, self._check_level(level, coarsest_ok=False))]

    def num_nodes_per_level(self) -> list[int]:
        """Node count of every level, finest first."""
        return [int(self.level(k).num_nodes) for k in range(self.num_levels)]

    def fine_index(self, level: int) -> Tensor:
        """For each node of ``level``, the index of the fine (``l0``) node it stands for.

        Composes the ``root`` maps of the levels in between; ``fine_index(0)`` is
        ``arange(N_0)``. Use it to read coarse positions, components or node types from
        fine-level tensors: ``pos_k = pos_0[data.fine_index(k)]``.

        Returns:
            ``LongTensor[N_level]``.
        """
        level = self._check_level(level)
        if level == 0:
            return torch.arange(int(self.level(0).num_nodes), device=self._device())
        idx = self.level(level).root
        for k in range(level - 1, 0, -1):
            idx = self.level(k).root[idx]
        return idx

    def _device(self) -> torch.device:
        for store in self.edge_stores:
            if "edge_index" in store:
                return store.edge_index.device
        return torch.device("cpu")

    # ---- batching --------------------------------------------------------------------
    def __inc__(
        self, key: str, value: Any, store: NodeStorage | EdgeStorage | None = None, *args, **kwargs
    ) -> Any:
        if key == "root" and isinstance(store, NodeStorage):
            m = _LEVEL_RE.match(store._key)
            if m is not None and int(m.group(1)) > 0:
                return self[level_name(int(m.group(1)) - 1)].num_nodes
        if key in ("contact_nbr", "face") and isinstance(store, NodeStorage):
            return store.num_nodes  # a contact table or triangles: indices into its own level
        return super().__inc__(key, value, store, *args, **kwargs)

    def __cat_dim__(
        self, key: str, value: Any, store: NodeStorage | EdgeStorage | None = None, *args, **kwargs
    ) -> Any:
        if key == "face" and isinstance(store, NodeStorage):
            return -1  # [3, T] triangles of the level, as in a PyG Data
        return super().__cat_dim__(key, value, store, *args, **kwargs)

    # ---- files -----------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write to ``path`` atomically, in a form that :meth:`load` reads with ``weights_only=True``.

        (``torch.save(data, path)`` works too, but, as for every PyG data object, reading it
        back needs ``torch.load(path, weights_only=False)``.)
        """
        atomic_torch_save(self.to_dict(), path)

    @classmethod
    def load(
        cls, path: str | os.PathLike, map_location: str | torch.device | None = None
    ) -> HierarchicalData:
        """Read a file written by :meth:`save` (safe ``weights_only`` unpickling)."""
        return cls.from_dict(torch.load(path, map_location=map_location, weights_only=True))

    # ---- display ---------------------------------------------------------------------
    def _num_edges(self, relation: str, level: int) -> int:
        """Edges of ``relation`` at ``level``; 0 where there is none (without creating the store)."""
        key = edge_type(relation, level)
        if key not in self.edge_types or "edge_index" not in self[key]:
            return 0
        return int(self[key].edge_index.size(1))

    def summary(self) -> str:
        """A table of nodes and edges per level."""
        rows = [("level", "nodes", *RELATIONS)]
        for k in range(self.num_levels):
            last = k == self.num_levels - 1
            rows.append(
                (
                    level_name(k),
                    str(self.level(k).num_nodes),
                    str(self._num_edges(MESH, k)),
                    str(self._num_edges(CONTACT, k)),
                    "-" if last else str(self._num_edges(DOWN, k)),
                    "-" if last else str(self._num_edges(UP, k)),
                )
            )
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
        return f"{type(self).__name__} with {self.num_levels} levels\n" + "\n".join(lines)
