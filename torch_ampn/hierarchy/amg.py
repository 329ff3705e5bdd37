"""AMG graph hierarchy (root-node smoothed aggregation from pyamg) for AMPNs."""

from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyamg
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from torch import Tensor

from torch_ampn.hierarchy.hierarchical_data import (
    CONTACT,
    DOWN,
    MESH,
    UP,
    HierarchicalData,
    edge_type,
    level_name,
)
from torch_ampn.utils.io import atomic_torch_save

#: Bump when the construction changes, so that cached hierarchies are rebuilt.
HIERARCHY_ALGORITHM_VERSION = 1

OPERATORS = ("adjacency", "laplacian")
#: pyamg prolongation smoother per operator: energy minimisation with CG needs an SPD
#: operator (the Laplacian); the adjacency ``A + I`` is indefinite, so it uses GMRES.
SMOOTHERS = {
    "adjacency": ("energy", {"krylov": "gmres"}),
    "laplacian": ("energy", {"krylov": "cg"}),
}
DOWN_EDGES = ("smoothed", "tentative")


@dataclass
class AMGLevel:
    """One coarsening step ``l -> l+1`` (all arrays on the CPU, NumPy/SciPy).

    Attributes:
        P: Smoothed prolongator, ``[n_l, n_{l+1}]`` CSR; ``R = P^T``.
        T: Tentative prolongator (aggregation), ``[n_l, n_{l+1}]`` CSR, one non-zero per row.
        root: Level-``l`` index of every coarse node's root, ``[n_{l+1}]``.
        A_coarse: Galerkin operator ``R A_l P``, ``[n_{l+1}, n_{l+1}]`` CSR.
        B_coarse: Near-null-space candidates of the coarse level, ``[n_{l+1}, 1]`` (pyamg's ``B``).
    """

    P: sp.csr_matrix
    T: sp.csr_matrix
    root: np.ndarray
    A_coarse: sp.csr_matrix
    B_coarse: np.ndarray


def validate_edge_index(edge_index: Tensor, num_nodes: int) -> None:
    """Raise ``ValueError`` with a readable message unless ``edge_index`` is a valid ``[2, E]`` graph."""
    if not isinstance(edge_index, Tensor):
        raise ValueError(f"edge_index must be a torch.Tensor, got {type(edge_index).__name__}")
    if edge_index.dtype not in (torch.int64, torch.int32):
        raise ValueError(f"edge_index must be an integer tensor (torch.long), got dtype {edge_index.dtype}")
    if edge_index.dim() != 2 or edge_index.size(0) != 2:
        raise ValueError(f"edge_index must have shape [2, E], got {list(edge_index.shape)}")
    if isinstance(num_nodes, bool) or not isinstance(num_nodes, (int, np.integer)):
        raise ValueError(f"num_nodes must be an int, got {type(num_nodes).__name__}")
    if num_nodes <= 0:
        raise ValueError(f"num_nodes must be positive (the graph is empty), got {num_nodes}")
    if edge_index.size(1) == 0:
        raise ValueError("edge_index has no edges: an AMG hierarchy needs a mesh graph with edges")
    lo, hi = int(edge_index.min()), int(edge_index.max())
    if lo < 0:
        raise ValueError(f"edge_index contains negative node index {lo}")
    if hi >= num_nodes:
        raise ValueError(f"edge_index contains node index {hi}, out of range for num_nodes={num_nodes}")


def mesh_operator(
    edge_index: Tensor, num_nodes: int, operator: str = "adjacency", laplacian_shift: float = 1e-2
) -> sp.csr_matrix:
    """The fine-level operator ``A_0`` the hierarchy is built from.

    Args:
        edge_index: ``[2, E]`` mesh edges, one or both directions (symmetrised here).
        num_nodes: ``N``.
        operator: ``"adjacency"``: binary adjacency with self-loops ``A + I`` (ROBIN's choice,
            the default); ``"laplacian"``: graph Laplacian ``D - A + shift * I``, symmetric
            positive definite, the classic AMG input.
        laplacian_shift: The ``shift`` of the Laplacian (makes it non-singular; isolated
            nodes and the constant mode of each component).

    Returns:
        Symmetric ``[N, N]`` CSR matrix (float64).
    """
    if operator not in OPERATORS:
        raise ValueError(f"operator must be one of {OPERATORS}, got {operator!r}")
    ei = edge_index.detach().cpu().long().numpy()
    keep = ei[0] != ei[1]
    row, col = ei[0, keep], ei[1, keep]
    adj = sp.coo_matrix((np.ones(row.size), (row, col)), shape=(num_nodes, num_nodes)).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float64).tocsr()
    eye = sp.identity(num_nodes, dtype=np.float64, format="csr")
    if operator == "adjacency":
        A = adj + eye
    else:
        if laplacian_shift <= 0:
            raise ValueError(f"laplacian_shift must be positive, got {laplacian_shift}")
        deg = np.asarray(adj.sum(axis=1)).ravel()
        A = sp.diags(deg + laplacian_shift, format="csr") - adj
    A = A.tocsr()
    A.sort_indices()
    return A


def _rootnode_step(
    A: sp.csr_matrix, B: np.ndarray, smooth: str | tuple
) -> tuple[sp.csr_matrix, sp.csr_matrix, np.ndarray, np.ndarray] | None:
    """Pyamg's first root-node aggregation step on one connected block: ``(P, T, roots, B_coarse)``."""
    ml = pyamg.aggregation.rootnode_solver(
        A, B=B, smooth=smooth, improve_candidates=None, max_levels=2, max_coarse=1, keep=True
    )
    if len(ml.levels) < 2:
        return None
    lv = ml.levels[0]
    nc = lv.P.shape[1]
    return lv.P.tocsr(), lv.T.tocsr(), np.asarray(lv.Cpts)[:nc], np.asarray(ml.levels[1].B)


def coarsen(
    A: sp.csr_matrix, B: np.ndarray | None = None, smooth: str | tuple = SMOOTHERS["adjacency"]
) -> AMGLevel | None:
    """One root-node smoothed-aggregation step with pyamg, or ``None`` if nothing coarsens.

    pyamg runs on every connected block of ``A`` (every component) separately, so a
    component's hierarchy does not depend on which other components share the graph: a
    batch of hierarchies equals the hierarchy of the disjoint union. ``B`` are pyamg's
    near-null-space candidates of this level (``None``: the constant vector, pyamg's
    default on the fine level); passing each step's ``B_coarse`` to the next step
    reproduces pyamg's own multi-level ``rootnode_solver`` on a connected graph. pyamg's
    candidate improvement (Gauss-Seidel sweeps on ``A B = 0``) is switched off: on
    ``A + I`` it diverges and fills ``P`` with NaN (seen on the paper-sized laminate), so
    ``B`` stays constant. ``smooth`` is pyamg's prolongation smoother. Blocks of one node
    (isolated nodes, which pyamg leaves out of every aggregate) become aggregates of their
    own. Coarse nodes are numbered in the order of their roots, so the coarse numbering
    follows the fine one.
    """
    n = A.shape[0]
    if B is None:
        B = np.ones((n, 1))
    off = A - sp.diags(A.diagonal(), format="csr")
    off.eliminate_zeros()
    num_blocks, labels = connected_components(off, directed=False)
    nodes_by_block = np.split(np.argsort(labels, kind="stable"), np.cumsum(np.bincount(labels))[:-1])

    rows_P, vals_P, cols_P, rows_T, cols_T, vals_T, roots, B_coarse = [], [], [], [], [], [], [], []
    nc, coarsened = 0, False
    for nodes in nodes_by_block:
        step = _rootnode_step(A[nodes][:, nodes].tocsr(), B[nodes], smooth) if nodes.size > 1 else None
        if step is None:  # one node (or nothing to coarsen): each node its own aggregate
            P_b = T_b = sp.identity(nodes.size, format="csr")
            root_b, B_b = np.arange(nodes.size), B[nodes]
        else:
            P_b, T_b, root_b, B_b = step
            coarsened = True
        for M, rows, cols, vals in (
            (P_b.tocoo(), rows_P, cols_P, vals_P),
            (T_b.tocoo(), rows_T, cols_T, vals_T),
        ):
            rows.append(nodes[M.row])
            cols.append(M.col + nc)
            vals.append(M.data)
        roots.append(nodes[root_b])
        B_coarse.append(B_b)
        nc += P_b.shape[1]
    if not coarsened:
        return None

    # Number coarse nodes by their roots' fine indices.
    root = np.concatenate(roots)
    order = np.argsort(root, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)

    def assemble(rows: list, cols: list, vals: list) -> sp.csr_matrix:
        M = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), rank[np.concatenate(cols)])), shape=(n, nc)
        )
        M.eliminate_zeros()
        M.sort_indices()
        return M

    P, T = assemble(rows_P, cols_P, vals_P), assemble(rows_T, cols_T, vals_T)
    R = P.T.tocsr()
    A_coarse = ((R @ A) @ P).tocsr()
    A_coarse.eliminate_zeros()
    A_coarse.sort_indices()
    return AMGLevel(P=P, T=T, root=root[order], A_coarse=A_coarse, B_coarse=np.concatenate(B_coarse)[order])


def amg_levels(
    A: sp.csr_matrix, max_levels: int, min_coarse_nodes: int, smooth: str | tuple = SMOOTHERS["adjacency"]
) -> list[AMGLevel]:
    """Coarsen ``A`` repeatedly with :func:`coarsen`.

    At most ``max_levels - 1`` steps; a step is kept only if its coarse level has at least
    ``min_coarse_nodes`` nodes and fewer nodes than the level above, else coarsening stops.
    """
    steps: list[AMGLevel] = []
    B = None
    while len(steps) + 1 < max_levels:
        step = coarsen(A, B, smooth)
        if step is None:
            break
        nc = step.P.shape[1]
        if nc < min_coarse_nodes or nc >= A.shape[0]:
            break
        steps.append(step)
        A, B = step.A_coarse, step.B_coarse
    return steps


def _off_diagonal_edges(A: sp.csr_matrix) -> Tensor:
    coo = A.tocoo()
    keep = coo.row != coo.col
    ei = np.stack([coo.row[keep], coo.col[keep]]).astype(np.int64)
    order = np.lexsort((ei[1], ei[0]))
    return torch.from_numpy(np.ascontiguousarray(ei[:, order]))


def _nonzeros(M: sp.csr_matrix) -> tuple[Tensor, Tensor]:
    coo = M.tocoo()
    order = np.lexsort((coo.col, coo.row))
    ei = np.stack([coo.row[order], coo.col[order]]).astype(np.int64)
    return torch.from_numpy(np.ascontiguousarray(ei)), torch.from_numpy(coo.data[order].astype(np.float32))


def _cache_key(edge_index: Tensor, num_nodes: int, params: dict) -> str:
    A = mesh_operator(edge_index, num_nodes, "adjacency")  # canonical (symmetric, sorted) topology
    h = hashlib.sha256()
    h.update(np.int64(num_nodes).tobytes())
    h.update(A.indptr.astype(np.int64).tobytes())
    h.update(A.indices.astype(np.int64).tobytes())
    h.update(repr(sorted(params.items())).encode())
    h.update(f"v{HIERARCHY_ALGORITHM_VERSION}-pyamg{pyamg.__version__}".encode())
    return h.hexdigest()


def _to_dict(A: sp.csr_matrix, steps: list[AMGLevel], down_edges: str) -> dict[str, Tensor]:
    """Flat tensor dictionary of a hierarchy (the on-disk cache format)."""
    out: dict[str, Tensor] = {"0/num_nodes": torch.tensor(A.shape[0]), "0/mesh": _off_diagonal_edges(A)}
    for k, step in enumerate(steps, start=1):
        out[f"{k}/num_nodes"] = torch.tensor(step.P.shape[1])
        out[f"{k}/mesh"] = _off_diagonal_edges(step.A_coarse)
        out[f"{k}/root"] = torch.from_numpy(step.root.astype(np.int64))
        out[f"{k}/down"], out[f"{k}/down_weight"] = _nonzeros(step.P if down_edges == "smoothed" else step.T)
    return out


def _from_dict(d: dict[str, Tensor]) -> HierarchicalData:
    """:class:`HierarchicalData` from the tensor dictionary of :func:`_to_dict`."""
    num_levels = sum(1 for key in d if key.endswith("/num_nodes"))
    h = HierarchicalData()
    for k in range(num_levels):
        lk = level_name(k)
        h[lk].num_nodes = int(d[f"{k}/num_nodes"])
        h[edge_type(MESH, k)].edge_index = d[f"{k}/mesh"]
        h[edge_type(CONTACT, k)].edge_index = torch.empty(2, 0, dtype=torch.long)
        if k > 0:
            h[lk].root = d[f"{k}/root"]
            down = d[f"{k}/down"]
            h[edge_type(DOWN, k - 1)].edge_index = down
            h[edge_type(DOWN, k - 1)].edge_weight = d[f"{k}/down_weight"]
            h[edge_type(UP, k - 1)].edge_index = down.flip(0)
            h[edge_type(UP, k - 1)].edge_weight = d[f"{k}/down_weight"]
    return h


def build_hierarchy(
    edge_index: Tensor,
    num_nodes: int,
    *,
    max_levels: int = 4,
    min_coarse_nodes: int = 16,
    operator: str = "adjacency",
    laplacian_shift: float = 1e-2,
    down_edges: str = "smoothed",
    cache_dir: str | os.PathLike | None = None,
) -> HierarchicalData:
    r"""Build the AMG graph hierarchy of a mesh with pyamg's root-node smoothed aggregation.

    Level 0 is the given mesh. Each coarsening step ``l -> l+1`` runs
    ``pyamg.aggregation.rootnode_solver`` on the level operator :math:`A_l` and keeps

    * coarse nodes: one per aggregate, each the aggregate's *root* fine node
      (``h["l{l+1}"].root``); nodes without neighbours are aggregates of their own,
    * coarse mesh edges: off-diagonal non-zeros of the Galerkin operator
      :math:`A_{l+1} = R_l A_l P_l` with :math:`R_l = P_l^\top`,
    * down edges ``l -> l+1``: non-zeros of the smoothed prolongator :math:`P_l`
      (or of the tentative aggregation operator with ``down_edges="tentative"``), with
      its values as ``edge_weight``; up edges are the same pairs reversed.

    Components (disconnected blocks of the graph) never share an aggregate. The result
    depends only on the topology and is deterministic.

    Args:
        edge_index: ``LongTensor[2, E]`` undirected mesh edges of all components (one or
            both directions; self-loops ignored).
        num_nodes: Number of fine nodes ``N``.
        max_levels: Maximum number of levels ``L + 1`` including the fine level.
        min_coarse_nodes: A coarse level is added only if it has at least this many nodes
            (and fewer than the level above); coarsening stops otherwise.
        operator: ``"adjacency"`` (``A + I``, default, as ROBIN) or ``"laplacian"``
            (``D - A + laplacian_shift * I``); see :func:`mesh_operator`.
        laplacian_shift: Diagonal shift for ``operator="laplacian"``.
        down_edges: ``"smoothed"`` (non-zeros of :math:`P`, default) or ``"tentative"``
            (one down edge per fine node, to its aggregate).
        cache_dir: If given, the hierarchy is stored there under a hash of the topology and
            the options, and loaded from there on later calls.

    Returns:
        :class:`HierarchicalData` with ``num_nodes``, mesh, empty contact, down and up edges
        per level and ``root`` on levels ``>= 1``; on ``edge_index``'s device.
    """
    validate_edge_index(edge_index, num_nodes)
    num_nodes = int(num_nodes)
    if max_levels < 1:
        raise ValueError(f"max_levels must be >= 1, got {max_levels}")
    if min_coarse_nodes < 1:
        raise ValueError(f"min_coarse_nodes must be >= 1, got {min_coarse_nodes}")
    if down_edges not in DOWN_EDGES:
        raise ValueError(f"down_edges must be one of {DOWN_EDGES}, got {down_edges!r}")
    if operator not in OPERATORS:
        raise ValueError(f"operator must be one of {OPERATORS}, got {operator!r}")
    device = edge_index.device

    cache_path = None
    if cache_dir is not None:
        params = dict(
            max_levels=max_levels,
            min_coarse_nodes=min_coarse_nodes,
            operator=operator,
            laplacian_shift=float(laplacian_shift) if operator == "laplacian" else None,
            down_edges=down_edges,
        )
        cache_path = Path(cache_dir) / f"hierarchy-{_cache_key(edge_index, num_nodes, params)[:32]}.pt"
        if cache_path.exists():
            try:
                return _from_dict(torch.load(cache_path, weights_only=True)).to(device)
            except Exception as err:  # unreadable or incomplete file: rebuild and overwrite it
                warnings.warn(f"ignoring unreadable hierarchy cache file {cache_path}: {err}", stacklevel=2)

    A = mesh_operator(edge_index, num_nodes, operator, laplacian_shift)
    steps = amg_levels(A, max_levels, min_coarse_nodes, SMOOTHERS[operator])
    tensors = _to_dict(A, steps, down_edges)
    if cache_path is not None:
        atomic_torch_save(tensors, cache_path)
    return _from_dict(tensors).to(device)
