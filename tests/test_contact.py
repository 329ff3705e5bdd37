"""Contact edges (component kNN within a radius) against an independent brute-force reference."""

import logging
import math
import os
import shutil

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

import torch_ampn.transforms._grid as grid_module
from torch_ampn.data import build_hierarchy, laminate_mesh, stacked_plates
from torch_ampn.transforms import (
    ComponentRadiusGraph,
    component_radius_graph,
    component_radius_table,
    plain_radius_graph,
    table_to_edge_index,
    torch_cluster_available,
)
from torch_ampn.transforms._grid import CellGrid
from torch_ampn.transforms._grid_search import auto_cell_size
from torch_ampn.transforms._native import native_available

CUDA = pytest.param(
    "cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")]
)
DEVICES = ["cpu", CUDA]


@pytest.fixture(autouse=True, scope="module", params=["native", "grid"])
def auto_backend(request):
    """Every test twice: ``backend="auto"`` on the CPU as the C search, and as the PyTorch grid."""
    import torch_ampn.transforms._checks as checks

    if request.param == "native" and not native_available():
        pytest.skip("no C compiler: the native search is not available")
    saved = checks.native_available
    if request.param == "grid":
        checks.native_available = lambda: False
    yield request.param
    checks.native_available = saved


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The inputs here are small: intra-op threads only add fork/join stalls on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---- reference (NumPy, float64, all pairs) --------------------------------------------------
def _dist2(pos: np.ndarray, targets: np.ndarray) -> np.ndarray:
    d = pos[None, :, :] - pos[targets, None, :]  # [B, N, 3]
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def reference_table(pos, comp, r, k, num_comp, batch=None, targets=None):
    """Rows ``targets`` of the table: per other component (increasing id), the k nearest within r,
    ordered by (distance, index); unused slots hold the node itself and mask False."""
    pos = np.asarray(pos, dtype=np.float64)
    comp = np.asarray(comp)
    n = len(pos)
    batch = np.zeros(n, dtype=np.int64) if batch is None else np.asarray(batch)
    targets = np.arange(n) if targets is None else np.asarray(targets)
    width = k * (num_comp - 1)
    nbr = np.repeat(targets[:, None], width, axis=1)
    mask = np.zeros((len(targets), width), dtype=bool)
    for start in range(0, len(targets), 256):
        rows = targets[start : start + 256]
        d2 = _dist2(pos, rows)
        d2[(d2 > r * r) | (batch[None, :] != batch[rows, None])] = np.inf
        for row_pos, i in enumerate(rows):
            slot = 0
            for c in range(num_comp):
                if c == comp[i]:
                    continue
                cand = np.flatnonzero((comp == c) & np.isfinite(d2[row_pos]))
                chosen = cand[np.lexsort((cand, d2[row_pos, cand]))][:k]
                nbr[start + row_pos, slot * k : slot * k + len(chosen)] = chosen
                mask[start + row_pos, slot * k : slot * k + len(chosen)] = True
                slot += 1
    return nbr, mask


def reference_edges(nbr, mask):
    target = np.repeat(np.arange(len(nbr))[:, None], nbr.shape[1], axis=1)
    return np.stack([nbr[mask], target[mask]])


def reference_radius(pos, r, batch=None, loop=False):
    pos = np.asarray(pos, dtype=np.float64)
    n = len(pos)
    batch = np.zeros(n, dtype=np.int64) if batch is None else np.asarray(batch)
    d2 = _dist2(pos, np.arange(n))
    ok = (d2 <= r * r) & (batch[None, :] == batch[:, None])
    if not loop:
        np.fill_diagonal(ok, False)
    target, source = np.nonzero(ok)  # row-major: sorted by target, then source
    return np.stack([source, target])


def assert_table(result, expected):
    nbr, mask = result
    assert nbr.dtype == torch.long and mask.dtype == torch.bool
    np.testing.assert_array_equal(mask.cpu().numpy(), expected[1])
    np.testing.assert_array_equal(nbr.cpu().numpy(), expected[0])


def random_cloud(n, num_comp, seed, extent=4.0, lattice=None, flat=False):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n, 3, generator=g, dtype=torch.float64) * extent
    if lattice is not None:  # many exact ties in distance
        pos = torch.round(pos / lattice) * lattice
    if flat:
        pos[:, 2] *= 0.05
    comp = torch.randint(0, num_comp, (n,), generator=g)
    return pos, comp


# ---- the table and the edge list --------------------------------------------------------------
@pytest.mark.parametrize("n", [1, 2, 17, 120, 400])
@pytest.mark.parametrize("num_comp", [1, 2, 3, 5, 8])
@pytest.mark.parametrize("k", [1, 3, 5])
def test_table_matches_reference_random(n, num_comp, k):
    seed = n * 100 + num_comp * 10 + k
    pos, comp = random_cloud(n, num_comp, seed)
    r = 0.4 + (seed % 7) * 0.2
    expected = reference_table(pos, comp, r, k, num_comp)
    assert_table(component_radius_table(pos, comp, r, k, num_components=num_comp), expected)


@pytest.mark.parametrize("cell_size", [None, 0.11, 0.25, 0.5, 1.3, 4.0])
@pytest.mark.parametrize("shape", ["cube", "flat", "lattice"])
def test_every_cell_size_gives_the_same_result(cell_size, shape):
    """The cell size only changes the search (passes, strips or columns), never the result."""
    pos, comp = random_cloud(
        500, 4, seed=7, lattice=0.25 if shape == "lattice" else None, flat=shape == "flat"
    )
    for k, r in [(2, 0.6), (4, 1.1)]:
        expected = reference_table(pos, comp, r, k, 4)
        assert_table(component_radius_table(pos, comp, r, k, num_components=4, cell_size=cell_size), expected)


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
def test_edge_list_order_and_content(k):
    pos, comp = random_cloud(300, 4, seed=k, lattice=0.2)
    nbr, mask = reference_table(pos, comp, 0.7, k, 4)
    ei = component_radius_graph(pos, comp, r=0.7, k=k)
    assert ei.dtype == torch.long and ei.shape[0] == 2
    np.testing.assert_array_equal(ei.numpy(), reference_edges(nbr, mask))
    assert not bool((comp[ei[0]] == comp[ei[1]]).any())  # never within a component
    # sorted by target, then by the source's component
    key = ei[1] * 10 + comp[ei[0]]
    assert bool((key[1:] >= key[:-1]).all())


def test_at_most_k_per_other_component():
    pos, comp = random_cloud(600, 5, seed=3, extent=2.0)
    k = 3
    ei = component_radius_graph(pos, comp, r=1.0, k=k)
    pairs = torch.stack([ei[1], comp[ei[0]]], 1)
    _, counts = torch.unique(pairs, dim=0, return_counts=True)
    assert int(counts.max()) == k
    assert ei.size(1) <= pos.size(0) * k * 4


def test_coincident_points_break_ties_by_index():
    base, comp = random_cloud(60, 3, seed=11)
    pos = torch.cat([base, base, base])  # every position three times
    comp = torch.cat([comp, torch.roll(comp, 1), torch.roll(comp, 2)])
    for k in [1, 2, 4]:
        expected = reference_table(pos, comp, 0.8, k, 3)
        assert_table(component_radius_table(pos, comp, 0.8, k), expected)
    # All nodes at one point: each picks the k smallest indices of every other component.
    same = torch.zeros(40, 3)
    comp = torch.arange(40) % 4
    nbr, mask = component_radius_table(same, comp, 1.0, 2)
    assert bool(mask.all())
    assert nbr[5].tolist() == [0, 4, 2, 6, 3, 7]  # node 5 is in component 1


def test_empty_components_and_fixed_width():
    pos, comp = random_cloud(200, 3, seed=5)
    comp = torch.tensor([0, 3, 6])[comp]  # ids 1, 2, 4, 5 (and 7) have no nodes
    expected = reference_table(pos, comp, 0.9, 2, 8)
    result = component_radius_table(pos, comp, 0.9, 2, num_components=8)
    assert result[0].shape == (200, 2 * 7)
    assert_table(result, expected)
    assert_table(component_radius_table(pos, comp, 0.9, 2), reference_table(pos, comp, 0.9, 2, 7))


def test_nodes_without_neighbours_in_range():
    pos = torch.tensor([[0.0, 0, 0], [10, 0, 0], [10.5, 0, 0], [20, 0, 0], [20, 3, 0]])
    comp = torch.tensor([0, 1, 0, 1, 0])
    nbr, mask = component_radius_table(pos, comp, r=1.0, k=2)
    assert mask.tolist() == [[False, False], [True, False], [True, False], [False, False], [False, False]]
    assert nbr[:, 0].tolist() == [0, 2, 1, 3, 4]  # dummy slots hold the node itself
    assert component_radius_graph(pos, comp, r=1.0, k=2).tolist() == [[2, 1], [1, 2]]


def test_single_component_and_empty_input():
    pos, _ = random_cloud(50, 1, seed=0)
    nbr, mask = component_radius_table(pos, torch.zeros(50, dtype=torch.long), 1.0, 3)
    assert nbr.shape == (50, 0) and mask.shape == (50, 0)
    assert component_radius_graph(pos, torch.zeros(50, dtype=torch.long), r=1.0).shape == (2, 0)
    nbr, mask = component_radius_table(
        torch.empty(0, 3), torch.empty(0, dtype=torch.long), 1.0, 2, num_components=3
    )
    assert nbr.shape == (0, 4) and mask.shape == (0, 4)
    assert plain_radius_graph(torch.empty(0, 3), 1.0).shape == (2, 0)


@pytest.mark.parametrize(
    "nx,layers,gap,r,k",
    [(6, 2, 0.5, 0.3, 1), (9, 3, 0.4, 0.35, 3), (12, 4, 0.5, 0.6, 2), (16, 6, 0.1, 0.25, 5)],
)
def test_stacked_plates(nx, layers, gap, r, k):
    mesh = stacked_plates(nx, nx - 2, layers, size=(1.0, 1.0), gap=gap)
    expected = reference_table(mesh.pos, mesh.component, r, k, layers)
    assert_table(component_radius_table(mesh.pos, mesh.component, r, k), expected)


def _check_rows(pos, comp, r, k, num_comp, rows, cell_size=None):
    nbr, mask = component_radius_table(pos, comp, r, k, num_components=num_comp, cell_size=cell_size)
    assert nbr.shape == (pos.size(0), k * (num_comp - 1))
    expected = reference_table(pos, comp, r, k, num_comp, targets=rows.numpy())
    np.testing.assert_array_equal(mask[rows].numpy(), expected[1])
    np.testing.assert_array_equal(nbr[rows].numpy(), expected[0])


def test_laminate_mesh_paper_size():
    """The paper-sized laminate (16k nodes, r = 3 mm, k = 3), checked on sampled rows."""
    mesh = laminate_mesh(scale=1)
    rows = torch.randperm(mesh.num_nodes, generator=torch.Generator().manual_seed(0))[:300].sort().values
    _check_rows(mesh.pos, mesh.component, 3.0, 3, 6, rows)


def test_dense_plates_take_several_passes():
    """Dense plates (many nodes per radius): small cells, several passes, slab bounds."""
    mesh = stacked_plates(40, 40, 4, size=(10.0, 10.0), gap=0.5)
    g = torch.Generator().manual_seed(1)
    pos = mesh.pos + 0.05 * torch.randn(mesh.pos.shape, generator=g) * torch.tensor([1.0, 1.0, 0.0])
    assert auto_cell_size(pos.double(), mesh.component, 3.0) < 1.0
    rows = torch.randperm(mesh.num_nodes, generator=g)[:300].sort().values
    _check_rows(pos, mesh.component, 3.0, 3, 4, rows)
    _check_rows(pos, mesh.component, 1.2, 5, 4, rows, cell_size=0.2)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_position_dtypes(dtype):
    pos, comp = random_cloud(150, 3, seed=2)
    pos = pos.to(dtype)
    expected = reference_table(pos.double(), comp, 0.8, 2, 3)  # distances of the given values
    assert_table(component_radius_table(pos, comp, 0.8, 2), expected)


def test_int32_labels_and_deterministic():
    pos, comp = random_cloud(300, 4, seed=9, lattice=0.25)
    a = component_radius_table(pos, comp.int(), 0.7, 3)
    b = component_radius_table(pos, comp, 0.7, 3)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


# ---- batches ----------------------------------------------------------------------------------
def test_batch_never_joins_graphs():
    pos_a, comp_a = random_cloud(150, 3, seed=1)
    pos_b, comp_b = random_cloud(100, 3, seed=2)  # overlapping positions: only batch separates them
    pos, comp = torch.cat([pos_a, pos_b]), torch.cat([comp_a, comp_b])
    batch = torch.cat([torch.zeros(150, dtype=torch.long), torch.ones(100, dtype=torch.long)])
    nbr, mask = component_radius_table(pos, comp, 0.8, 2, batch=batch)
    nbr_a, mask_a = component_radius_table(pos_a, comp_a, 0.8, 2)
    nbr_b, mask_b = component_radius_table(pos_b, comp_b, 0.8, 2)
    assert torch.equal(nbr, torch.cat([nbr_a, nbr_b + 150])) and torch.equal(
        mask, torch.cat([mask_a, mask_b])
    )
    assert_table((nbr, mask), reference_table(pos, comp, 0.8, 2, 3, batch=batch))
    shuffled = torch.randperm(250, generator=torch.Generator().manual_seed(0))  # unsorted batch ids too
    expected = reference_table(pos[shuffled], comp[shuffled], 0.8, 2, 3, batch=batch[shuffled])
    assert_table(
        component_radius_table(pos[shuffled], comp[shuffled], 0.8, 2, batch=batch[shuffled]), expected
    )


# ---- plain radius graph -------------------------------------------------------------------------
@pytest.mark.parametrize("n,r,lattice", [(1, 1.0, None), (80, 0.5, None), (300, 0.9, 0.25), (500, 0.3, None)])
@pytest.mark.parametrize("loop", [False, True])
def test_plain_radius_graph(n, r, lattice, loop):
    pos, _ = random_cloud(n, 1, seed=n, lattice=lattice)
    ei = plain_radius_graph(pos, r, loop=loop)
    np.testing.assert_array_equal(ei.numpy(), reference_radius(pos, r, loop=loop))


def test_plain_radius_graph_batch_and_counts():
    pos, comp = random_cloud(300, 3, seed=4)
    batch = (torch.arange(300) >= 120).long()
    ei = plain_radius_graph(pos, 0.7, batch=batch)
    np.testing.assert_array_equal(ei.numpy(), reference_radius(pos, 0.7, batch=batch))
    knn = component_radius_graph(pos, comp, 0.7, k=100, batch=batch)  # k large: all cross pairs
    cross = ei[:, comp[ei[0]] != comp[ei[1]]]
    assert torch.equal(torch.sort(knn[1] * 300 + knn[0]).values, torch.sort(cross[1] * 300 + cross[0]).values)


# ---- internals: lookup tables, chunking, extreme extents ------------------------------------------
def test_sparse_lookup_and_small_chunks_agree(monkeypatch):
    pos, comp = random_cloud(400, 4, seed=12, extent=30.0)
    r, k = 1.5, 3
    expected = reference_table(pos, comp, r, k, 4)
    monkeypatch.setattr(grid_module, "DENSE_TABLE_MIN", 0)  # force binary search over sorted keys
    grid = CellGrid(pos, comp, 4, 0.2, r)
    assert grid.start is None
    assert_table(component_radius_table(pos, comp, r, k, cell_size=0.2), expected)
    monkeypatch.setattr(grid_module, "MAX_RANGES", 7)
    monkeypatch.setattr(grid_module, "MAX_PAIRS", 5)
    assert_table(component_radius_table(pos, comp, r, k), expected)
    assert_table(component_radius_table(pos, comp, r, k, cell_size=0.5), expected)
    np.testing.assert_array_equal(plain_radius_graph(pos, r).numpy(), reference_radius(pos, r))


def test_grid_layouts():
    """Flat groups use the thin layout (runs along the middle axis, slab bounds), others columns."""
    mesh = stacked_plates(8, 8, 3, gap=0.5)
    thin = CellGrid(mesh.pos.double(), mesh.component, 3, 0.4, 1.0)
    assert thin.thin and thin.num_box == 1
    node, group = torch.tensor([0, 0, 90]), torch.tensor([1, 2, 0])  # node 0 in plate 0, 90 in plate 1
    assert torch.allclose(thin.floor2(node, group), torch.tensor([0.25, 1.0, 0.25], dtype=torch.float64))
    pos, comp = random_cloud(300, 3, seed=1)
    column = CellGrid(pos, comp, 3, 0.4, 1.0)
    assert not column.thin and column.num_box == 2
    assert bool((column.floor2(node, group) == 0).all())
    # Plates farther apart than r have no contact edges at all.
    assert component_radius_graph(mesh.pos, mesh.component, r=0.45, k=3).shape == (2, 0)


def test_far_apart_clusters_and_tiny_radius():
    """Extents far beyond ``r`` make the grid coarsen its cells to fit int64 keys."""
    pos, comp = random_cloud(120, 3, seed=8, extent=1e-3)
    pos = torch.cat([pos, pos + 1e9])
    comp = torch.cat([comp, comp])
    expected = reference_table(pos, comp, 4e-4, 2, 3)
    assert_table(component_radius_table(pos, comp, 4e-4, 2), expected)


# ---- the transform on a hierarchy ---------------------------------------------------------------
def _hierarchy(nx=14, ny=12, layers=3, seed=0):
    mesh = stacked_plates(nx, ny, layers, size=(7.0, 6.0), gap=0.5)
    h = build_hierarchy(mesh.edge_index(), mesh.num_nodes, max_levels=3, min_coarse_nodes=4)
    g = torch.Generator().manual_seed(seed)
    h["l0"].pos = mesh.pos + 0.2 * torch.randn(mesh.pos.shape, generator=g)
    h["l0"].component = mesh.component
    return h


def test_transform_fills_every_level_from_root_positions():
    h = _hierarchy()
    assert h.num_levels == 3
    out = ComponentRadiusGraph(r=0.9, k=2)(h)
    for level in range(h.num_levels):
        idx = h.fine_index(level)
        pos, comp = h["l0"].pos[idx], h["l0"].component[idx]
        nbr, mask = reference_table(pos, comp, 0.9, 2, 3)
        ei = out.contact(level).edge_index
        np.testing.assert_array_equal(ei.numpy(), reference_edges(nbr, mask))
        assert ei.size(1) > 0
    assert h.contact(0).edge_index.size(1) == 0  # the input is not modified


def test_transform_level_radius_scale():
    h = _hierarchy()
    cases = [
        (None, [0.6, 0.6, 0.6], False),
        (None, [0.6, 0.6, 0.6], True),  # one search over all levels
        ([1.0, 1.0, 1.0], [0.6, 0.6, 0.6], True),
        (2.0, [0.6, 1.2, 2.4], True),  # different radii: one search per level
        ([1.0, 1.5, 3.0], [0.6, 0.9, 1.8], False),
    ]
    for scale, radii, merge in cases:
        transform = ComponentRadiusGraph(r=0.6, k=1, level_radius_scale=scale, merge_levels=merge)
        out = transform(h)
        for level, radius in enumerate(radii):
            assert math.isclose(transform.level_radius(level), radius)
            idx = h.fine_index(level)
            expected = component_radius_graph(h["l0"].pos[idx], h["l0"].component[idx], radius, 1)
            assert torch.equal(out.contact(level).edge_index, expected)
    with pytest.raises(ValueError, match="level_radius_scale has 2 entries"):
        ComponentRadiusGraph(r=0.6, level_radius_scale=[1.0, 2.0])(h)
    with pytest.raises(ValueError, match="level_radius_scale"):
        ComponentRadiusGraph(r=0.6, level_radius_scale=[1.0, -2.0])


def test_transform_on_a_batch_equals_the_single_results():
    h1, h2 = _hierarchy(seed=1), _hierarchy(nx=10, ny=9, layers=2, seed=2)
    transform = ComponentRadiusGraph(r=0.9, k=3, num_components=3, static=True)
    merged = ComponentRadiusGraph(r=0.9, k=3, num_components=3, static=True, merge_levels=True)
    singles = [transform(h1), transform(h2)]
    batch = transform(Batch.from_data_list([h1, h2]))
    batch_merged = merged(Batch.from_data_list([h1, h2]))
    for level in range(3):
        assert torch.equal(batch_merged.level(level).contact_nbr, batch.level(level).contact_nbr)
        assert torch.equal(batch_merged.contact(level).edge_index, batch.contact(level).edge_index)
    for level in range(3):
        offset = singles[0].level(level).num_nodes
        expected = torch.cat(
            [singles[0].contact(level).edge_index, singles[1].contact(level).edge_index + offset], 1
        )
        assert torch.equal(batch.contact(level).edge_index, expected)
        nbr = torch.cat([singles[0].level(level).contact_nbr, singles[1].level(level).contact_nbr + offset])
        assert torch.equal(batch.level(level).contact_nbr, nbr)
        assert batch.level(level).contact_mask.shape == (batch.level(level).num_nodes, 3 * 2)


def test_transform_static_tables_and_repr():
    h = _hierarchy()
    out = ComponentRadiusGraph(r=0.9, k=2, static=True)(h)
    for level in range(out.num_levels):
        nbr, mask = out.level(level).contact_nbr, out.level(level).contact_mask
        assert nbr.shape == mask.shape == (out.level(level).num_nodes, 2 * 2)
        assert torch.equal(table_to_edge_index(nbr, mask), out.contact(level).edge_index)
    assert repr(ComponentRadiusGraph(r=0.25)) == (
        "ComponentRadiusGraph(r=0.25, k=3, level_radius_scale=None, num_components=None, "
        "static=False, backend='auto', merge_levels=False, mode='component_knn', positions='current', "
        "edge_features=False)"
    )


def test_transform_radius_mode_links_every_pair_within_r_on_every_level():
    """The conventional radius graph: all pairs (j, i), j != i, within r, any component; brute force."""
    h = _hierarchy()
    out = ComponentRadiusGraph(r=0.9, mode="radius")(h)
    knn = ComponentRadiusGraph(r=0.9, k=2)(h)
    for level in range(h.num_levels):
        pos = h["l0"].pos[h.fine_index(level)].double()
        dist = torch.cdist(pos, pos)
        target, source = torch.nonzero((dist <= 0.9) & ~torch.eye(len(pos), dtype=torch.bool), as_tuple=True)
        expected = {(int(j), int(i)) for j, i in zip(source, target, strict=True)}
        ei = out.contact(level).edge_index
        assert {(int(j), int(i)) for j, i in ei.t()} == expected and ei.size(1) == len(expected)
        assert ei.size(1) >= knn.contact(level).edge_index.size(1)
    assert out.contact(0).edge_index.size(1) > knn.contact(0).edge_index.size(1)  # same-component pairs too
    with pytest.raises(ValueError, match="mode"):
        ComponentRadiusGraph(r=0.9, mode="knn")
    with pytest.raises(ValueError, match="fixed-size"):
        ComponentRadiusGraph(r=0.9, mode="radius", static=True)


def test_transform_initial_positions_give_the_same_edges_at_every_state():
    h = _hierarchy()
    h["l0"].pos0 = h["l0"].pos.clone()
    static = ComponentRadiusGraph(r=0.9, k=2, positions="initial")
    first = [static(h).contact(level).edge_index.clone() for level in range(h.num_levels)]
    moved = h.clone()
    noise = torch.randn(h["l0"].pos.shape, generator=torch.Generator().manual_seed(3))
    moved["l0"].pos = h["l0"].pos + 0.5 * noise
    current = ComponentRadiusGraph(r=0.9, k=2)
    for level in range(h.num_levels):
        assert torch.equal(static(moved).contact(level).edge_index, first[level])
        assert torch.equal(current(h).contact(level).edge_index, first[level])
    changed = [not torch.equal(current(moved).contact(k).edge_index, first[k]) for k in range(h.num_levels)]
    assert any(changed)
    with pytest.raises(ValueError, match="positions"):
        ComponentRadiusGraph(r=0.9, positions="start")
    with pytest.raises(ValueError, match="pos0"):
        static(_hierarchy())


def test_transform_needs_positions_and_components():
    h = _hierarchy()
    del h["l0"].component
    with pytest.raises(ValueError, match="component"):
        ComponentRadiusGraph(r=0.9)(h)
    with pytest.raises(ValueError, match="HierarchicalData"):
        ComponentRadiusGraph(r=0.9)(torch.zeros(3))


# ---- validation -------------------------------------------------------------------------------
GOOD_POS = torch.rand(10, 3)
GOOD_COMP = torch.arange(10) % 2


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(pos=torch.rand(10, 2)), r"pos must have shape \[N, 3\]"),
        (dict(pos=torch.rand(10)), r"pos must have shape \[N, 3\]"),
        (dict(pos=torch.ones(10, 3, dtype=torch.long)), "pos must be a floating point"),
        (dict(pos=[[0.0, 0.0, 0.0]]), "pos must be a torch.Tensor"),
        (dict(pos=torch.full((10, 3), float("nan"))), "NaN or infinite"),
        (dict(pos=torch.tensor([[float("inf"), 0, 0]] * 10)), "NaN or infinite"),
        (dict(component=torch.zeros(10)), "component must be an integer"),
        (dict(component=torch.zeros(10, dtype=torch.bool)), "component must be an integer"),
        (dict(component=torch.zeros(9, dtype=torch.long)), "component has 9 entries but pos has 10"),
        (dict(component=torch.zeros(10, 1, dtype=torch.long)), r"component must have shape \[N\]"),
        (dict(component=-GOOD_COMP), "component contains negative ids"),
        (dict(r=0.0), "r must be positive"),
        (dict(r=-1.0), "r must be positive"),
        (dict(r=float("inf")), "r must be positive and finite"),
        (dict(r=float("nan")), "r must be positive and finite"),
        (dict(r="3"), "r must be a number"),
        (dict(k=0), "k must be an integer >= 1"),
        (dict(k=2.5), "k must be an integer >= 1"),
        (dict(num_components=1), "component contains id 1 but num_components=1"),
        (dict(num_components=0), "num_components must be an integer >= 1"),
        (dict(batch=torch.zeros(10)), "batch must be an integer"),
        (dict(batch=-torch.ones(10, dtype=torch.long)), "batch contains negative ids"),
        (dict(batch=torch.zeros(3, dtype=torch.long)), "batch has 3 entries"),
        (dict(backend="kdtree"), "backend must be one of"),
        (dict(cell_size=0.0), "cell_size must be positive"),
    ],
)
def test_bad_input_raises_value_error(kwargs, match):
    args = dict(pos=GOOD_POS, component=GOOD_COMP, r=0.5, k=2) | kwargs
    with pytest.raises(ValueError, match=match):
        component_radius_table(**args)
    with pytest.raises(ValueError, match=match):
        component_radius_graph(**args)


def test_bad_input_plain_and_transform():
    with pytest.raises(ValueError, match="r must be positive"):
        plain_radius_graph(GOOD_POS, r=0.0)
    with pytest.raises(ValueError, match="NaN"):
        plain_radius_graph(torch.full((4, 3), float("nan")), r=1.0)
    with pytest.raises(ValueError, match="k must be an integer >= 1"):
        ComponentRadiusGraph(r=1.0, k=0)
    with pytest.raises(ValueError, match="r must be positive"):
        ComponentRadiusGraph(r=-3.0)
    with pytest.raises(TypeError, match="'r'"):  # no default radius: it depends on the mesh's units
        ComponentRadiusGraph()
    with pytest.raises(TypeError, match="'r'"):
        component_radius_graph(GOOD_POS, GOOD_COMP)
    with pytest.raises(TypeError, match="'r'"):
        component_radius_table(GOOD_POS, GOOD_COMP, k=2)
    with pytest.raises(ValueError, match="backend must be one of"):
        ComponentRadiusGraph(r=1.0, backend="nope")
    with pytest.raises(ValueError, match="equal shape"):
        table_to_edge_index(torch.zeros(3, 2, dtype=torch.long), torch.zeros(3, 1, dtype=torch.bool))


# ---- other backends and devices -------------------------------------------------------------------
@pytest.mark.skipif(not torch_cluster_available(), reason="torch-cluster not installed")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_torch_cluster_backend_equals_grid(seed):
    pos, comp = random_cloud(700, 5, seed=seed, lattice=0.25 if seed == 1 else None)
    batch = (torch.arange(700) >= 300).long()
    for k, r in [(1, 0.4), (3, 0.8)]:
        grid = component_radius_table(pos, comp, r, k, batch=batch, backend="grid")
        cluster = component_radius_table(pos, comp, r, k, batch=batch, backend="torch_cluster")
        assert torch.equal(grid[0], cluster[0]) and torch.equal(grid[1], cluster[1])
    assert torch.equal(plain_radius_graph(pos, 0.5, backend="torch_cluster"), plain_radius_graph(pos, 0.5))


def test_torch_cluster_backend_on_the_laminate():
    pytest.importorskip("torch_cluster")
    mesh = laminate_mesh(scale=1)
    grid = component_radius_table(mesh.pos, mesh.component, 3.0, 3)
    cluster = component_radius_table(mesh.pos, mesh.component, 3.0, 3, backend="torch_cluster")
    assert torch.equal(grid[0], cluster[0]) and torch.equal(grid[1], cluster[1])


@pytest.mark.parametrize("device", DEVICES)
def test_devices(device):
    pos, comp = random_cloud(600, 4, seed=21, lattice=0.2)
    batch = (torch.arange(600) >= 250).long()
    expected = reference_table(pos, comp, 0.6, 3, 4, batch=batch)
    for cell_size in [None, 0.15]:
        result = component_radius_table(
            pos.to(device), comp.to(device), 0.6, 3, batch=batch.to(device), cell_size=cell_size
        )
        assert result[0].device.type == device
        assert_table(result, expected)
    ei = plain_radius_graph(pos.to(device), 0.6, batch=batch.to(device))
    np.testing.assert_array_equal(ei.cpu().numpy(), reference_radius(pos, 0.6, batch=batch))
    h = _hierarchy().to(device)
    out = ComponentRadiusGraph(r=0.9, k=2)(h)
    assert out.contact(1).edge_index.device.type == device


# ---- the native (C) search ------------------------------------------------------------------------
def test_auto_is_the_native_search_on_the_cpu_and_explicit_backends_agree(auto_backend):
    from torch_ampn.transforms._checks import check_backend

    assert check_backend("auto", torch.device("cpu")) == auto_backend
    assert check_backend("auto", torch.device("meta")) == "grid"  # no native search off the CPU
    assert check_backend("auto") == "grid"  # callers without a native search
    if auto_backend == "grid":  # (the native search is switched off in this pass)
        return
    pos, comp = random_cloud(400, 5, seed=4, lattice=0.25)
    batch = (torch.arange(400) >= 150).long()
    native = component_radius_table(pos, comp, 0.7, 3, batch=batch, backend="native")
    grid = component_radius_table(pos, comp, 0.7, 3, batch=batch, backend="grid")
    assert torch.equal(native[0], grid[0]) and torch.equal(native[1], grid[1])
    with pytest.raises(ValueError, match="backend='native' is not implemented"):
        plain_radius_graph(pos, 0.5, backend="native")
    with pytest.raises(ValueError, match="mode='radius' has no native search"):
        ComponentRadiusGraph(r=1.0, mode="radius", backend="native")


def test_native_search_with_coarser_cells_than_the_radius(monkeypatch, auto_backend):
    """A far-flung cloud would need too many cells of edge r: the cells grow, the result stays."""
    import torch_ampn.transforms._native as native

    if auto_backend == "grid":
        pytest.skip("the native search is switched off in this pass")
    pos, comp = random_cloud(300, 3, seed=12, lattice=0.25)
    pos[:5] += 1000.0  # a few far nodes stretch the bounding box
    expected = reference_table(pos, comp, 0.6, 2, 3)
    monkeypatch.setattr(native, "MAX_CELLS", 64)
    assert_table(component_radius_table(pos, comp, 0.6, 2, backend="native"), expected)


def test_without_a_c_compiler_auto_falls_back_to_the_grid(monkeypatch, tmp_path, auto_backend):
    """No compiler (``$CC`` names none, nothing cached): the PyTorch grid, and a clear error for 'native'."""
    import torch_ampn.transforms._checks as checks
    import torch_ampn.transforms._native as native

    if auto_backend == "grid":
        pytest.skip("the native search is switched off in this pass")
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setenv("TORCH_AMPN_CACHE", str(tmp_path / "cache"))
    native._library.cache_clear()
    try:
        assert not native.native_available() and not checks.native_available()
        assert checks.check_backend("auto", torch.device("cpu")) == "grid"
        pos, comp = random_cloud(50, 3, seed=1)
        with pytest.raises(ValueError, match="backend='native' needs a C compiler"):
            component_radius_table(pos, comp, 0.5, 1, backend="native")
        assert_table(component_radius_table(pos, comp, 0.5, 1), reference_table(pos, comp, 0.5, 1, 3))
        # with a compiler the library is built into the cache folder
        monkeypatch.delenv("CC")
        native._library.cache_clear()
        assert native.native_available()
        assert len(list((tmp_path / "cache").glob("ampn_native_*.so"))) == 1
    finally:
        native._library.cache_clear()


def test_no_compile_switch_takes_the_grid_and_compiles_nothing(monkeypatch, tmp_path, caplog, auto_backend):
    """``TORCH_AMPN_NO_COMPILE=1``: no compiler run and the brute-force tables; a build is logged once."""
    import torch_ampn.transforms._checks as checks
    import torch_ampn.transforms._native as native

    if auto_backend == "grid":
        pytest.skip("the native search is switched off in this pass")
    runs = []
    real_run = native.subprocess.run
    monkeypatch.setattr(native.subprocess, "run", lambda *args, **kwargs: runs.append(args))
    monkeypatch.setenv("TORCH_AMPN_NO_COMPILE", "1")
    cache = tmp_path / "cache"
    monkeypatch.setenv("TORCH_AMPN_CACHE", str(cache))
    pos, comp = random_cloud(300, 4, seed=21, lattice=0.25)
    batch = (torch.arange(300) >= 120).long()
    expected = reference_table(pos, comp, 0.7, 3, 4, batch=batch.numpy())
    caplog.set_level(logging.INFO, logger=native.__name__)
    native._library.cache_clear()
    try:
        assert not native.native_available() and checks.check_backend("auto", torch.device("cpu")) == "grid"
        pure = component_radius_table(pos, comp, 0.7, 3, batch=batch)
        assert_table(pure, expected)
        with pytest.raises(ValueError, match="TORCH_AMPN_NO_COMPILE=1"):
            component_radius_table(pos, comp, 0.7, 3, backend="native")
        assert runs == [] and not cache.exists()
        assert not [rec for rec in caplog.records if rec.name == native.__name__]  # nothing to say
        # without the switch: one build into the cache, said once, and the same table
        monkeypatch.delenv("TORCH_AMPN_NO_COMPILE")
        monkeypatch.setattr(native.subprocess, "run", real_run)
        native._library.cache_clear()
        compiled = component_radius_table(pos, comp, 0.7, 3, batch=batch, backend="native")
        assert torch.equal(compiled[0], pure[0]) and torch.equal(compiled[1], pure[1])
        native._library.cache_clear()  # a new process: the cached library, no second build
        assert native.native_available()
        builds = [rec for rec in caplog.records if rec.getMessage().startswith("compiling the C contact")]
        assert len(builds) == 1 and str(cache) in builds[0].getMessage()
        assert builds[0].args[0] == (os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc"))
    finally:
        native._library.cache_clear()
