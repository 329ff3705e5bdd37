r"""Steady problems on random unstructured meshes whose answer at a node depends on far-away data.

The reach benchmark (``benchmarks/reach/``) and notebook 04 use them to show where a graph
hierarchy pays. Every sample is its own random mesh (a jittered lattice, Delaunay-triangulated)
with its own data, and its target is a P1 finite-element solution assembled and solved here with
SciPy (float64, then stored as float32):

* :func:`laplace_sample`: :math:`\Delta u = 0` in the unit square, :math:`u = g` on the boundary,
  ``g`` a random smooth periodic function of the arc length (optionally plus a random constant). The interior
  depends on all of the boundary: a node in the middle is about ``sqrt(N) / 2`` mesh edges away.
* :func:`elasticity_sample`: plane-stress linear elasticity of a ``2 x 1`` plate clamped on its
  left edge and pulled on its right edge by a random smooth prescribed displacement; the
  displacement in between depends on both edges (``sqrt(2 N)`` edges apart).
* :func:`smoothing_sample`: the control, whose answer is local: the consistent mass matrix applied
  to a noisy node field, divided by the lumped mass (a one-ring weighted average).

Each returns a PyG ``Data`` with ``pos [N, 2]``, ``edge_index [2, E]`` (both directions),
``x [N, F]`` (inputs), ``y [N, C]`` (target), ``mask [N]`` (the nodes the error is measured on),
``source [N]`` (the nodes whose data the answer depends on: for :func:`hop_distance`) and
``face [3, T]``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import Delaunay
from torch import Tensor
from torch_geometric.data import Data

#: Input channels, output channels and what they are, per problem. Every problem is linear in its
#: data: scaling the ``data_channels`` of ``x`` by ``a`` scales ``y`` by ``a`` (the augmentation
#: of ``benchmarks/reach/run.py --augment``, checked in ``tests/test_reach_problems.py``).
PROBLEMS = {
    "laplace": {
        "in_channels": 4,
        "out_channels": 1,
        "inputs": "boundary flag, g on the boundary, x, y",
        "data_channels": [1],
    },
    "elasticity": {
        "in_channels": 6,
        "out_channels": 2,
        "inputs": "clamped flag, loaded flag, prescribed displacement (x, y) on the loaded edge, x, y",
        "data_channels": [2, 3],
    },
    "smoothing": {
        "in_channels": 4,
        "out_channels": 1,
        "inputs": "noisy field, boundary flag, x, y",
        "data_channels": [0],
    },
}


# ---- meshes ---------------------------------------------------------------------------------------
def random_mesh(
    num_nodes: int, width: float, height: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A random unstructured triangle mesh of the rectangle ``[0, width] x [0, height]``.

    About ``num_nodes`` nodes: the boundary evenly spaced, the interior a lattice of the same
    spacing jittered by up to 0.35 spacings, Delaunay-triangulated.

    Returns:
        ``(pos [N, 2] float64, triangles [T, 3] int64)``, triangles counter-clockwise.
    """
    if num_nodes < 16:
        raise ValueError(f"random_mesh: num_nodes must be >= 16, got {num_nodes}")
    h = math.sqrt(width * height / num_nodes)  # node spacing
    nx, ny = max(round(width / h), 2), max(round(height / h), 2)
    xs, ys = np.linspace(0, width, nx + 1), np.linspace(0, height, ny + 1)
    boundary = np.concatenate(
        [
            np.stack([xs[:-1], np.zeros(nx)], 1),  # bottom, left to right
            np.stack([np.full(ny, width), ys[:-1]], 1),  # right, bottom to top
            np.stack([xs[::-1][:-1], np.full(nx, height)], 1),  # top, right to left
            np.stack([np.zeros(ny), ys[::-1][:-1]], 1),  # left, top to bottom
        ]
    )
    gx, gy = np.meshgrid(xs[1:-1], ys[1:-1], indexing="ij")
    inner = np.stack([gx.ravel(), gy.ravel()], 1)
    inner = inner + rng.uniform(-0.35, 0.35, inner.shape) * np.array([width / nx, height / ny])
    pos = np.concatenate([boundary, inner])
    tri = Delaunay(pos).simplices.astype(np.int64)
    cross = _signed_area(pos[tri]) * 2
    tri = tri[cross > 1e-12 * h * h]  # drop degenerate slivers on the boundary, if any
    flip = cross[cross > 1e-12 * h * h] < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return pos, tri


def mesh_edges(tri: np.ndarray, num_nodes: int) -> Tensor:
    """Both directions of every triangle edge, sorted: ``LongTensor[2, E]``."""
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    key = np.unique(e[:, 0] * num_nodes + e[:, 1])
    return torch.from_numpy(np.stack([key // num_nodes, key % num_nodes]))


# ---- P1 finite elements ---------------------------------------------------------------------------
def _signed_area(p: np.ndarray) -> np.ndarray:
    """Signed areas ``[T]`` of triangles ``p [T, 3, 2]`` (positive: counter-clockwise)."""
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def _gradients(pos: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the three hat functions of every triangle ``[T, 3, 2]`` and the areas ``[T]``."""
    p = pos[tri]  # [T, 3, 2]
    d = np.stack([p[:, 1] - p[:, 2], p[:, 2] - p[:, 0], p[:, 0] - p[:, 1]], 1)  # edge opposite each vertex
    area = _signed_area(p)
    grad = np.stack([-d[..., 1], d[..., 0]], -1) / (2 * area[:, None, None])  # [T, 3, 2]: rot90(d) / 2A
    return grad, area


def _assemble(tri: np.ndarray, local: np.ndarray, num_dofs: int, dofs_per_node: int = 1) -> sp.csr_matrix:
    """Sum element matrices ``[T, k, k]`` into a CSR ``[num_dofs, num_dofs]``."""
    dofs = (tri[:, :, None] * dofs_per_node + np.arange(dofs_per_node)).reshape(len(tri), -1)  # [T, k]
    k = dofs.shape[1]
    rows, cols = np.repeat(dofs, k, 1).ravel(), np.tile(dofs, k).ravel()
    return sp.coo_matrix((local.ravel(), (rows, cols)), (num_dofs, num_dofs)).tocsr()


def stiffness_matrix(pos: np.ndarray, tri: np.ndarray) -> sp.csr_matrix:
    r"""P1 stiffness matrix of :math:`-\Delta`: :math:`K_{ij} = \int \nabla\phi_i \cdot \nabla\phi_j`."""
    grad, area = _gradients(pos, tri)
    return _assemble(tri, np.einsum("tik,tjk->tij", grad, grad) * area[:, None, None], len(pos))


def mass_matrix(pos: np.ndarray, tri: np.ndarray) -> sp.csr_matrix:
    r"""P1 mass matrix :math:`M_{ij} = \int \phi_i \phi_j` (``A (1 + \delta_{ij}) / 12`` per triangle)."""
    _, area = _gradients(pos, tri)
    local = (np.ones((3, 3)) + np.eye(3))[None] * (area / 12)[:, None, None]
    return _assemble(tri, local, len(pos))


def elasticity_matrix(
    pos: np.ndarray, tri: np.ndarray, young: float = 1.0, poisson: float = 0.3
) -> sp.csr_matrix:
    """P1 plane-stress stiffness ``[2N, 2N]``, degrees of freedom ``(u_x, u_y)`` interleaved per node."""
    grad, area = _gradients(pos, tri)
    T = len(tri)
    B = np.zeros((T, 3, 6))  # strains (xx, yy, 2xy) from (u0x, u0y, u1x, ...)
    B[:, 0, 0::2] = grad[..., 0]
    B[:, 1, 1::2] = grad[..., 1]
    B[:, 2, 0::2] = grad[..., 1]
    B[:, 2, 1::2] = grad[..., 0]
    nu = poisson
    D = young / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    local = np.einsum("tki,kl,tlj->tij", B, D, B) * area[:, None, None]
    return _assemble(tri, local, 2 * len(pos), 2)


def hop_distance(edge_index: Tensor, source: Tensor, num_nodes: int | None = None) -> Tensor:
    """Mesh edges from every node to the nearest ``source`` node (multi-source BFS): ``LongTensor[N]``.

    Nodes that no source reaches get ``-1``.
    """
    n = int(num_nodes if num_nodes is not None else source.numel())
    ei = edge_index.cpu().numpy()
    graph = sp.coo_matrix((np.ones(ei.shape[1]), (ei[0], ei[1])), (n, n)).tocsr()
    sources = np.flatnonzero(source.cpu().numpy())
    if sources.size == 0:
        raise ValueError("hop_distance: no source node")
    dist = dijkstra(graph, directed=False, indices=sources, unweighted=True, min_only=True)
    return torch.from_numpy(np.where(np.isfinite(dist), dist, -1).astype(np.int64))


# ---- random smooth data ---------------------------------------------------------------------------
def _fourier(t: np.ndarray, modes: int, rng: np.random.Generator, period: float) -> np.ndarray:
    """A random smooth periodic function of ``t`` (period ``period``), mode ``k`` with amplitude ``1 / k``."""
    a, b = rng.standard_normal((2, modes))
    k = np.arange(1, modes + 1)
    phase = 2 * np.pi * np.outer(t, k) / period  # [n, modes]
    return (np.cos(phase) * a + np.sin(phase) * b) @ (1 / k)


def _data(
    pos: np.ndarray, tri: np.ndarray, x: np.ndarray, y: np.ndarray, mask: np.ndarray, source: np.ndarray
) -> Data:
    n = len(pos)
    return Data(
        pos=torch.tensor(pos, dtype=torch.float32),
        edge_index=mesh_edges(tri, n),
        x=torch.tensor(x, dtype=torch.float32),
        y=torch.tensor(y, dtype=torch.float32),
        mask=torch.from_numpy(mask),
        source=torch.from_numpy(source),
        face=torch.from_numpy(np.ascontiguousarray(tri.T)),
    )


def _boundary(pos: np.ndarray, width: float, height: float) -> np.ndarray:
    tol = 1e-9 * max(width, height)
    x, y = pos[:, 0], pos[:, 1]
    return (x < tol) | (x > width - tol) | (y < tol) | (y > height - tol)


def laplace_sample(num_nodes: int, seed: int, modes: int = 6, constant: float = 0.0) -> Data:
    r"""Laplace's equation with random smooth Dirichlet data: one sample (see the module docs).

    ``g(s) = c + \sum_{k=1}^{modes} (a_k \cos 2\pi k s / 4 + b_k \sin 2\pi k s / 4) / k`` of the
    arc length ``s`` round the unit square, ``a, b ~ N(0, 1)``, ``c ~ N(0, constant^2)``. With a
    constant, the interior is mostly ``c``: the boundary's mean, a far harder target for every
    network (see docs/generic.md).

    Returns:
        ``Data``: ``x [N, 4]`` (boundary flag, ``g`` on the boundary and 0 inside, ``x``, ``y``),
        ``y [N, 1]`` (``u``), ``mask`` the interior, ``source`` the boundary.
    """
    rng = np.random.default_rng(seed)
    pos, tri = random_mesh(num_nodes, 1.0, 1.0, rng)
    on_boundary = _boundary(pos, 1.0, 1.0)
    px, py = pos[:, 0], pos[:, 1]
    s = np.select([py < 1e-9, px > 1 - 1e-9, py > 1 - 1e-9], [px, 1 + py, 3 - px], 4 - py)  # arc length
    g = constant * rng.standard_normal() + _fourier(s, modes, rng, 4.0)
    u = np.where(on_boundary, g, 0.0)
    K = stiffness_matrix(pos, tri)
    inner = ~on_boundary
    u[inner] = spla.spsolve(K[inner][:, inner].tocsc(), -K[inner][:, on_boundary] @ g[on_boundary])
    x = np.stack([on_boundary.astype(float), np.where(on_boundary, g, 0.0), px, py], 1)
    return _data(pos, tri, x, u[:, None], inner, on_boundary)


def elasticity_sample(num_nodes: int, seed: int, modes: int = 3, poisson: float = 0.3) -> Data:
    r"""A ``2 x 1`` plate clamped at ``x = 0`` and pulled at ``x = 2`` by a random smooth displacement.

    Plane stress, Young's modulus 1, top and bottom edges free. The far edge's prescribed
    displacement ``d(y) = (d_x, d_y)`` (each component a random constant plus ``modes`` random
    cosine modes of amplitude ``1 / k``) loads the plate, as the punch's prescribed motion
    drives a forming simulation; the displacement in between depends on both edges, ``sqrt(2 N)``
    mesh edges apart.

    Returns:
        ``Data``: ``x [N, 6]`` (clamped flag, loaded flag, ``d_x``, ``d_y`` on the loaded edge
        and 0 elsewhere, ``x``, ``y``), ``y [N, 2]`` (the displacement), ``mask`` the nodes of
        neither edge, ``source`` the loaded edge.
    """
    width, height = 2.0, 1.0
    rng = np.random.default_rng(seed)
    pos, tri = random_mesh(num_nodes, width, height, rng)
    n = len(pos)
    clamped = pos[:, 0] < 1e-9
    loaded = pos[:, 0] > width - 1e-9
    k = np.arange(1, modes + 1)

    def profile(y: np.ndarray) -> np.ndarray:
        return rng.standard_normal() + np.cos(np.pi * np.outer(y, k)) @ (rng.standard_normal(modes) / k)

    prescribed = np.where(
        loaded[:, None], np.stack([profile(pos[:, 1]), profile(pos[:, 1])], 1), 0.0
    )  # [N, 2]
    K = elasticity_matrix(pos, tri, 1.0, poisson)
    fixed = np.repeat(clamped | loaded, 2)
    u = prescribed.ravel().copy()
    u[~fixed] = spla.spsolve(K[~fixed][:, ~fixed].tocsc(), -K[~fixed][:, fixed] @ u[fixed])
    x = np.concatenate([np.stack([clamped, loaded], 1), prescribed, pos], 1).astype(float)
    return _data(pos, tri, x, u.reshape(n, 2), ~(clamped | loaded), loaded)


def smoothing_sample(num_nodes: int, seed: int) -> Data:
    r"""The control with a local answer: ``y = M_L^{-1} M z`` of a noisy node field ``z ~ N(0, 1)``.

    ``M`` is the P1 consistent mass matrix and ``M_L`` its row sums (the lumped mass): at every
    node a weighted mean of ``z`` over its one-ring.

    Returns:
        ``Data``: ``x [N, 4]`` (``z``, boundary flag, ``x``, ``y``), ``y [N, 1]``, ``mask`` every
        node, ``source`` every node.
    """
    rng = np.random.default_rng(seed)
    pos, tri = random_mesh(num_nodes, 1.0, 1.0, rng)
    z = rng.standard_normal(len(pos))
    M = mass_matrix(pos, tri)
    y = (M @ z) / np.asarray(M.sum(axis=1)).ravel()
    on_boundary = _boundary(pos, 1.0, 1.0)
    x = np.stack([z, on_boundary, pos[:, 0], pos[:, 1]], 1).astype(float)
    every = np.ones(len(pos), dtype=bool)
    return _data(pos, tri, x, y[:, None], every, every)


SAMPLERS = {"laplace": laplace_sample, "elasticity": elasticity_sample, "smoothing": smoothing_sample}


def reach_sample(problem: str, num_nodes: int, seed: int) -> Data:
    """One sample of ``problem`` (``"laplace"``, ``"elasticity"`` or ``"smoothing"``), see the module docs."""
    if problem not in SAMPLERS:
        raise ValueError(f"reach_sample: problem must be one of {sorted(SAMPLERS)}, got {problem!r}")
    return SAMPLERS[problem](num_nodes, seed)
