"""build_hierarchy against independent references: pyamg run directly, scipy Galerkin products."""

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp
import torch
from torch_geometric.data import Batch

from torch_ampn.data import build_hierarchy, laminate_mesh, stacked_plates
from torch_ampn.hierarchy import amg as hierarchy_module
from torch_ampn.hierarchy.amg import SMOOTHERS, mesh_operator


def _pattern(ei: torch.Tensor, n: int, m: int | None = None) -> sp.csr_matrix:
    ei = ei.numpy()
    return sp.csr_matrix((np.ones(ei.shape[1]), (ei[0], ei[1])), shape=(n, m or n))


def _pairs(M: sp.spmatrix, off_diagonal: bool = False) -> set:
    M = sp.coo_matrix(M)
    M.eliminate_zeros()
    return {(i, j) for i, j in zip(M.row.tolist(), M.col.tolist(), strict=True) if not off_diagonal or i != j}


def _edge_pairs(ei: torch.Tensor) -> set:
    return set(map(tuple, ei.t().tolist()))


def _down_matrix(h, k: int) -> sp.csr_matrix:
    d = h.down(k)
    n, m = int(h.level(k).num_nodes), int(h.level(k + 1).num_nodes)
    ei = d.edge_index.numpy()
    return sp.csr_matrix((d.edge_weight.double().numpy(), (ei[0], ei[1])), shape=(n, m))


def _grid_graph(nx=18, ny=14):
    m = stacked_plates(nx, ny, num_layers=1)
    return m.edge_index(), m.num_nodes


@pytest.fixture(scope="module")
def laminate():
    m = laminate_mesh()
    ei = m.edge_index()
    return m, ei, build_hierarchy(ei, m.num_nodes)


def test_paper_mesh_gives_three_coarse_levels(laminate):
    _, _, h = laminate
    assert h.num_levels == 4  # L = 3, as reported in the seed paper
    sizes = h.num_nodes_per_level()
    assert sizes[0] == 16390 and all(a > b for a, b in zip(sizes, sizes[1:], strict=False))


@pytest.mark.parametrize("operator", ["adjacency", "laplacian"])
def test_single_component_matches_pyamg_multilevel_solver(operator):
    """On a connected mesh our level-by-level construction is pyamg's own hierarchy."""
    ei, n = _grid_graph()
    h = build_hierarchy(ei, n, max_levels=3, min_coarse_nodes=4, operator=operator)
    A = mesh_operator(ei, n, operator)
    ml = pyamg.aggregation.rootnode_solver(
        A, max_levels=3, max_coarse=4, keep=True, improve_candidates=None, smooth=SMOOTHERS[operator]
    )
    assert h.num_levels == len(ml.levels) == 3
    for k in range(2):
        lv = ml.levels[k]
        P_ref = lv.P.tocsr()
        assert np.isfinite(P_ref.data).all()
        assert torch.equal(h.level(k + 1).root, torch.from_numpy(np.asarray(lv.Cpts).astype(np.int64)))
        assert _edge_pairs(h.down(k).edge_index) == _pairs(P_ref)
        np.testing.assert_allclose(_down_matrix(h, k).toarray(), P_ref.toarray(), atol=1e-6)
        RAP = (lv.R @ lv.A) @ P_ref  # Galerkin operator with scipy
        assert _edge_pairs(h.mesh(k + 1).edge_index) == _pairs(RAP, off_diagonal=True)


def test_every_fine_node_in_exactly_one_aggregate(laminate):
    m, ei, _ = laminate
    h = build_hierarchy(ei, m.num_nodes, down_edges="tentative")
    for k in range(h.num_levels - 1):
        src = h.down(k).edge_index[0]
        assert torch.equal(torch.bincount(src, minlength=int(h.level(k).num_nodes)), torch.ones_like(src))
        # Tentative aggregation with a constant candidate: weights scaled so that the root is 1.
        assert torch.allclose(h.down(k).edge_weight, torch.ones(src.numel()))


def test_roots_have_a_down_edge_to_their_own_coarse_node(laminate):
    _, _, h = laminate
    for k in range(h.num_levels - 1):
        root = h.level(k + 1).root
        P = _down_matrix(h, k)
        # Root-node property: the prolongator restricted to the roots is the identity.
        np.testing.assert_allclose(P[root.numpy()].toarray(), np.eye(P.shape[1]), atol=1e-6)
        pairs = _edge_pairs(h.down(k).edge_index)
        assert all((int(r), c) in pairs for c, r in enumerate(root))


def test_coarse_mesh_edges_are_galerkin_sparsity(laminate):
    """Level k+1 mesh edges = off-diagonal structure of R A_k P with R = P^T (scipy, structural product)."""
    _, _, h = laminate
    for k in range(h.num_levels - 1):
        n = int(h.level(k).num_nodes)
        A_pattern = _pattern(h.mesh(k).edge_index, n) + sp.identity(n)
        P_pattern = _pattern(h.down(k).edge_index, n, int(h.level(k + 1).num_nodes))
        RAP = P_pattern.T @ A_pattern @ P_pattern  # non-negative: no cancellation
        assert _edge_pairs(h.mesh(k + 1).edge_index) == _pairs(RAP, off_diagonal=True)
        assert _edge_pairs(h.up(k).edge_index) == {(j, i) for i, j in _edge_pairs(h.down(k).edge_index)}
        assert torch.equal(h.up(k).edge_weight, h.down(k).edge_weight)


def test_aggregates_never_cross_components(laminate):
    m, _, h = laminate
    for k in range(h.num_levels - 1):
        comp_fine = m.component[h.fine_index(k)]
        comp_coarse = m.component[h.fine_index(k + 1)]
        src, dst = h.down(k).edge_index
        assert torch.equal(comp_fine[src], comp_coarse[dst])
        a, b = h.mesh(k + 1).edge_index
        assert torch.equal(comp_coarse[a], comp_coarse[b])


def test_isolated_nodes_get_their_own_aggregate():
    ei, n = _grid_graph(12, 12)
    isolated = torch.tensor([n, n + 1, n + 5])
    # Nodes n..n+5 exist; n+2, n+3 and n+4 form a tiny chain, the others have no edge.
    ei = torch.cat([ei, torch.tensor([[n + 2, n + 3], [n + 3, n + 4]])], 1)
    h = build_hierarchy(ei, n + 6, max_levels=3, min_coarse_nodes=4)
    assert h.num_levels == 3
    fine = isolated
    for k in range(h.num_levels - 1):
        src, dst = h.down(k).edge_index
        counts = torch.bincount(src, minlength=int(h.level(k).num_nodes))
        assert (counts >= 1).all(), f"level {k} has nodes without a down edge"
        root = h.level(k + 1).root
        for f in fine.tolist():
            assert counts[f] == 1
            c = int(dst[src == f])
            assert int(root[c]) == f  # its own aggregate, rooted at itself
        fine = torch.tensor([int(dst[src == f]) for f in fine.tolist()])
        # Isolated coarse nodes have no coarse mesh edges either.
        assert not torch.isin(fine, h.mesh(k + 1).edge_index.flatten()).any()


def test_batch_equals_hierarchy_of_disjoint_union():
    m1, m2 = stacked_plates(30, 30, 2), stacked_plates(25, 35, 3)
    e1, e2 = m1.edge_index(), m2.edge_index()
    h1 = build_hierarchy(e1, m1.num_nodes, max_levels=3)
    h2 = build_hierarchy(e2, m2.num_nodes, max_levels=3)
    hu = build_hierarchy(torch.cat([e1, e2 + m1.num_nodes], 1), m1.num_nodes + m2.num_nodes, max_levels=3)
    b = Batch.from_data_list([h1, h2])
    assert b.num_levels == hu.num_levels == 3
    for k in range(3):
        assert b.level(k).num_nodes == hu.level(k).num_nodes
        assert torch.equal(b.mesh(k).edge_index, hu.mesh(k).edge_index)
        if k > 0:
            assert torch.equal(b.level(k).root, hu.level(k).root)
        if k < 2:
            for store_b, store_u in ((b.down(k), hu.down(k)), (b.up(k), hu.up(k))):
                assert torch.equal(store_b.edge_index, store_u.edge_index)
                assert torch.allclose(store_b.edge_weight, store_u.edge_weight, atol=1e-6)


def test_one_direction_and_both_directions_give_the_same_hierarchy():
    ei, n = _grid_graph()
    one_way = ei[:, ei[0] < ei[1]]
    with_self_loops = torch.cat([one_way, torch.arange(n).repeat(2, 1)], 1)
    h_both = build_hierarchy(ei, n)
    for other in (build_hierarchy(one_way, n), build_hierarchy(with_self_loops, n)):
        for k in range(h_both.num_levels):
            assert torch.equal(other.mesh(k).edge_index, h_both.mesh(k).edge_index)


def test_deterministic(laminate):
    m, ei, h = laminate
    perm = torch.randperm(ei.size(1), generator=torch.Generator().manual_seed(0))
    h2 = build_hierarchy(ei[:, perm], m.num_nodes)  # edge order does not matter either
    for k in range(h.num_levels - 1):
        assert torch.equal(h.down(k).edge_index, h2.down(k).edge_index)
        assert torch.equal(h.down(k).edge_weight, h2.down(k).edge_weight)
        assert torch.equal(h.mesh(k + 1).edge_index, h2.mesh(k + 1).edge_index)


def test_max_levels_and_min_coarse_nodes():
    ei, n = _grid_graph(30, 30)
    assert build_hierarchy(ei, n, max_levels=1).num_levels == 1
    assert build_hierarchy(ei, n, max_levels=2).num_levels == 2
    h = build_hierarchy(ei, n, max_levels=10, min_coarse_nodes=1)
    sizes = h.num_nodes_per_level()
    assert sizes[-1] >= 1 and h.num_levels > 3
    h20 = build_hierarchy(ei, n, max_levels=10, min_coarse_nodes=20)
    assert min(h20.num_nodes_per_level()) >= 20
    assert h20.num_levels < h.num_levels


def test_smoothed_down_edges_superset_of_tentative(laminate):
    m, ei, h = laminate
    ht = build_hierarchy(ei, m.num_nodes, down_edges="tentative")
    for k in range(h.num_levels - 1):
        assert _edge_pairs(ht.down(k).edge_index) <= _edge_pairs(h.down(k).edge_index)
        assert ht.down(k).edge_index.size(1) == int(h.level(k).num_nodes)
        assert torch.isfinite(h.down(k).edge_weight).all()


def test_cache_round_trip(tmp_path, monkeypatch):
    ei, n = _grid_graph()
    h = build_hierarchy(ei, n, cache_dir=tmp_path)
    files = list(tmp_path.glob("hierarchy-*.pt"))
    assert len(files) == 1
    assert not list(tmp_path.glob("*.tmp"))

    def fail(*args, **kwargs):
        raise AssertionError("hierarchy was rebuilt instead of read from the cache")

    monkeypatch.setattr(hierarchy_module, "amg_levels", fail)
    h2 = build_hierarchy(ei.flip(0), n, cache_dir=tmp_path)  # same topology, other edge order
    for k in range(h.num_levels):
        assert torch.equal(h.mesh(k).edge_index, h2.mesh(k).edge_index)
    for k in range(h.num_levels - 1):
        assert torch.equal(h.down(k).edge_weight, h2.down(k).edge_weight)
        assert torch.equal(h.level(k + 1).root, h2.level(k + 1).root)
    monkeypatch.undo()
    build_hierarchy(ei, n, cache_dir=tmp_path, down_edges="tentative")  # other options: other file
    assert len(list(tmp_path.glob("hierarchy-*.pt"))) == 2


def test_corrupt_cache_file_is_rebuilt(tmp_path):
    ei, n = _grid_graph()
    h = build_hierarchy(ei, n, cache_dir=tmp_path)
    (path,) = tmp_path.glob("hierarchy-*.pt")
    path.write_bytes(b"not a torch file")
    with pytest.warns(UserWarning, match="unreadable hierarchy cache file"):
        h2 = build_hierarchy(ei, n, cache_dir=tmp_path)
    assert torch.equal(h.mesh(1).edge_index, h2.mesh(1).edge_index)
    build_hierarchy(ei, n, cache_dir=tmp_path)  # rewritten: no warning now


@pytest.mark.parametrize(
    "edge_index,num_nodes,match",
    [
        (torch.tensor([[0, 1], [1, 5]]), 5, "out of range"),
        (torch.tensor([[0, -1], [1, 2]]), 5, "negative"),
        (torch.empty(2, 0, dtype=torch.long), 5, "no edges"),
        (torch.tensor([[0, 1], [1, 2]]), 0, "empty"),
        (torch.tensor([[0.0, 1.0], [1.0, 2.0]]), 5, "dtype"),
        (torch.tensor([0, 1, 2]), 5, "shape"),
        (torch.tensor([[0, 1], [1, 2], [2, 3]]), 5, "shape"),
        (np.array([[0, 1], [1, 2]]), 5, "torch.Tensor"),
        (torch.tensor([[0, 1], [1, 2]]), 2.5, "num_nodes must be an int"),
    ],
)
def test_invalid_input_raises(edge_index, num_nodes, match):
    with pytest.raises(ValueError, match=match):
        build_hierarchy(edge_index, num_nodes)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(max_levels=0), "max_levels"),
        (dict(min_coarse_nodes=0), "min_coarse_nodes"),
        (dict(operator="dense"), "operator"),
        (dict(down_edges="all"), "down_edges"),
        (dict(operator="laplacian", laplacian_shift=0.0), "laplacian_shift"),
    ],
)
def test_invalid_options_raise(kwargs, match):
    ei, n = _grid_graph(4, 4)
    with pytest.raises(ValueError, match=match):
        build_hierarchy(ei, n, **kwargs)
