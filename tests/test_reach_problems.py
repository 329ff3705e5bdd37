"""The reach benchmark's FE problems (torch_ampn.datasets) against hand-computed and exact references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.sparse.linalg import spsolve

from torch_ampn.datasets import elasticity_sample, hop_distance, laplace_sample, random_mesh, smoothing_sample
from torch_ampn.datasets.reach import elasticity_matrix, mass_matrix, stiffness_matrix


def test_single_triangle_matrices_by_hand():
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    tri = np.array([[0, 1, 2]])
    K = stiffness_matrix(pos, tri).toarray()
    # the right triangle with legs 1: grad phi = (-1, -1), (1, 0), (0, 1), area 1/2
    np.testing.assert_allclose(K, 0.5 * np.array([[2, -1, -1], [-1, 1, 0], [-1, 0, 1]]), atol=1e-14)
    M = mass_matrix(pos, tri).toarray()
    np.testing.assert_allclose(M, np.array([[2, 1, 1], [1, 2, 1], [1, 1, 2]]) / 24, atol=1e-14)


def test_random_mesh_is_a_valid_triangulation():
    pos, tri = random_mesh(2000, 2.0, 1.0, np.random.default_rng(0))
    p = pos[tri]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    assert (area > 0).all()  # counter-clockwise, no slivers
    assert area.sum() == pytest.approx(2.0, rel=1e-12)  # the triangles tile the rectangle
    assert abs(len(pos) - 2000) < 150


def test_laplace_reproduces_linear_data_exactly_and_converges_on_a_harmonic_quadratic():
    # P1 elements are exact for a linear function; boundary data g = 1 + 2x - 3y
    pos, tri = random_mesh(800, 1.0, 1.0, np.random.default_rng(1))
    on_boundary = (pos.min(1) < 1e-9) | (pos.max(1) > 1 - 1e-9)
    K = stiffness_matrix(pos, tri)
    for exact, tol in (
        (lambda p: 1 + 2 * p[:, 0] - 3 * p[:, 1], 1e-10),
        (lambda p: p[:, 0] ** 2 - p[:, 1] ** 2, 2e-3),
    ):
        g = exact(pos)
        inner = ~on_boundary
        u = g.copy()
        u[inner] = spsolve(K[inner][:, inner].tocsc(), -K[inner][:, on_boundary] @ g[on_boundary])
        assert np.abs(u - g).max() < tol


def test_laplace_sample_satisfies_the_discrete_equations():
    data = laplace_sample(1500, seed=3)
    n = data.num_nodes
    u = data.y[:, 0].double().numpy()
    boundary = data.x[:, 0].bool().numpy()
    np.testing.assert_allclose(u[boundary], data.x[boundary, 1].double().numpy(), atol=1e-6)
    K = stiffness_matrix(data.pos.double().numpy(), data.face.t().numpy())
    residual = (K @ u)[~boundary]
    assert np.abs(residual).max() < 1e-5 * np.abs(u).max()
    # a discrete maximum principle on a Delaunay mesh: the interior stays within the boundary's range
    assert u[~boundary].max() <= u[boundary].max() + 1e-6 and u[~boundary].min() >= u[boundary].min() - 1e-6
    assert data.mask.sum() == n - boundary.sum()


def test_elasticity_has_rigid_modes_and_balances_the_load():
    pos, tri = random_mesh(400, 2.0, 1.0, np.random.default_rng(2))
    K = elasticity_matrix(pos, tri)
    x, y = pos[:, 0], pos[:, 1]
    for mode in (
        np.stack([np.ones_like(x), 0 * x], 1),
        np.stack([0 * x, np.ones_like(x)], 1),
        np.stack([-y, x], 1),
    ):
        assert np.abs(K @ mode.ravel()).max() < 1e-10  # translations and the rotation cost no energy
    data = elasticity_sample(1200, seed=4)
    pos, u = data.pos.double().numpy(), data.y.double().numpy()
    K = elasticity_matrix(pos, data.face.t().numpy())
    force = (K @ u.ravel()).reshape(-1, 2)  # zero on free nodes, the reactions on the two edges
    clamped, loaded = data.x[:, 0].bool().numpy(), data.x[:, 1].bool().numpy()
    free = ~(clamped | loaded)
    assert np.abs(force[free]).max() < 1e-4 * np.abs(force).max()  # u is stored in float32
    np.testing.assert_allclose(force[clamped].sum(0), -force[loaded].sum(0), rtol=1e-5, atol=1e-8)  # balance
    np.testing.assert_allclose(u[loaded], data.x[loaded, 2:4].double().numpy(), atol=1e-6)
    assert np.abs(u[clamped]).max() == 0
    assert torch.equal(data.mask, torch.from_numpy(free))


def test_elasticity_under_uniform_stretch_matches_the_hand_solution():
    # pulled by d = (e L, 0) with free lateral edges: far from the clamp, u_x = e x (Saint-Venant)
    pos, tri = random_mesh(3000, 2.0, 1.0, np.random.default_rng(5))
    K = elasticity_matrix(pos, tri, 1.0, 0.0)  # Poisson's ratio 0: no lateral contraction, exact
    clamped, loaded = pos[:, 0] < 1e-9, pos[:, 0] > 2 - 1e-9
    fixed = np.repeat(clamped | loaded, 2)
    u = np.zeros(2 * len(pos))
    u[0::2][loaded] = 0.02
    u[~fixed] = spsolve(K[~fixed][:, ~fixed].tocsc(), -K[~fixed][:, fixed] @ u[fixed])
    np.testing.assert_allclose(u[0::2], 0.01 * pos[:, 0], atol=1e-10)
    np.testing.assert_allclose(u[1::2], 0.0, atol=1e-10)


def test_smoothing_is_a_weighted_mean_of_the_one_ring():
    data = smoothing_sample(1000, seed=5)
    z, y = data.x[:, 0].double(), data.y[:, 0].double()
    ei = data.edge_index
    lo = torch.full_like(z, float("inf")).scatter_reduce(0, ei[1], z[ei[0]], "amin").minimum(z)
    hi = torch.full_like(z, -float("inf")).scatter_reduce(0, ei[1], z[ei[0]], "amax").maximum(z)
    assert ((y >= lo - 1e-5) & (y <= hi + 1e-5)).all()  # within its one-ring's range
    M = mass_matrix(data.pos.double().numpy(), data.face.t().numpy())
    np.testing.assert_allclose((M @ np.ones(data.num_nodes)) / np.asarray(M.sum(1)).ravel(), 1.0)


def test_hop_distance_against_breadth_first_search_by_hand():
    # a path 0 - 1 - 2 - 3 - 4 and an isolated node 5
    ei = torch.tensor([[0, 1, 1, 2, 2, 3, 3, 4], [1, 0, 2, 1, 3, 2, 4, 3]])
    source = torch.tensor([True, False, False, False, True, False])
    assert hop_distance(ei, source, 6).tolist() == [0, 1, 2, 1, 0, -1]
    with pytest.raises(ValueError, match="no source"):
        hop_distance(ei, torch.zeros(6, dtype=torch.bool), 6)


def test_samples_are_deterministic_and_differ_by_seed():
    a, b, c = laplace_sample(500, 7), laplace_sample(500, 7), laplace_sample(500, 8)
    assert torch.equal(a.y, b.y) and torch.equal(a.pos, b.pos)
    assert not torch.equal(a.x[:, 1], c.x[:, 1])


@pytest.mark.parametrize("problem", ["laplace", "elasticity", "smoothing"])
def test_the_target_is_linear_in_the_data_channels(problem):
    """What ``--augment`` relies on: scaling ``x[:, data_channels]`` by ``a`` scales ``y`` by ``a``.

    Checked against the sample's own FE system solved again in float64 with the data scaled
    (Laplace, elasticity: the Dirichlet values on the data nodes; smoothing: the noisy field).
    """
    from torch_ampn.datasets import PROBLEMS, reach_sample

    data, a = reach_sample(problem, 600, seed=3), -2.5
    channels = PROBLEMS[problem]["data_channels"]
    pos, tri = data.pos.double().numpy(), data.face.t().numpy()
    x, y = data.x.double().numpy(), data.y.double().numpy()
    n = len(pos)
    if problem == "smoothing":
        M = mass_matrix(pos, tri)
        again = (M @ (a * x[:, 0])) / np.asarray(M.sum(axis=1)).ravel()
        np.testing.assert_allclose(again, a * y[:, 0], atol=1e-5)
        return
    dofs = len(channels)
    K = stiffness_matrix(pos, tri) if problem == "laplace" else elasticity_matrix(pos, tri, 1.0, 0.3)
    fixed = np.repeat(~data.mask.numpy(), dofs)  # the Dirichlet nodes: data (scaled) or clamped (0)
    u = np.zeros(n * dofs)
    u[fixed] = a * y.reshape(-1)[fixed]
    np.testing.assert_allclose(
        a * x[:, channels][data.source.numpy()], u.reshape(n, dofs)[data.source.numpy()], atol=1e-5
    )
    u[~fixed] = spsolve(K[~fixed][:, ~fixed].tocsc(), -K[~fixed][:, fixed] @ u[fixed])
    np.testing.assert_allclose(u.reshape(n, dofs), a * y, atol=1e-4)
