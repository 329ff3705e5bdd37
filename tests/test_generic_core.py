"""The generic core on meshes that are not forming (AMGHierarchy, ComponentRadiusGraph, AMPN): public API."""

import pytest
import torch
from torch_geometric.data import Batch, Data
from torch_geometric.loader import DataLoader
from torch_geometric.transforms import Delaunay, FaceToEdge

from torch_ampn.hierarchy import HierarchicalData, check_level_counts
from torch_ampn.nn import AMPN
from torch_ampn.transforms import AMGHierarchy, ComponentRadiusGraph


def brute_force_contact(pos: torch.Tensor, component: torch.Tensor, r: float, k: int) -> set[tuple[int, int]]:
    """Edges (j, i): for every node i and every other component, its k nearest nodes j within r."""
    dist = torch.cdist(pos, pos)
    expected = set()
    for i in range(pos.size(0)):
        for c in component.unique().tolist():
            if c == component[i]:
                continue
            cand = torch.nonzero((component == c) & (dist[i] <= r)).squeeze(1)
            nearest = cand[dist[i, cand].argsort()[:k]]
            expected |= {(int(j), i) for j in nearest}
    return expected


def random_mesh(num_nodes: int, seed: int, features: int = 5) -> Data:
    """A Delaunay mesh of random points in the unit square (float64), with x, y and a graph attribute."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(num_nodes, 2, generator=g, dtype=torch.float64)
    x = torch.randn(num_nodes, features, generator=g, dtype=torch.float64)
    y = torch.sin(3 * pos[:, :1]) * torch.cos(2 * pos[:, 1:])  # [N, 1] a smooth field
    return FaceToEdge()(Delaunay()(Data(pos=pos, x=x, y=y, scale=torch.tensor([[float(seed)]]))))


@pytest.mark.parametrize("num_nodes", [300, 2000])
def test_amg_hierarchy_carries_positions_attributes_and_relative_position_features(num_nodes):
    data = random_mesh(num_nodes, seed=num_nodes)
    h = AMGHierarchy(max_levels=3, min_coarse_nodes=4)(data)
    assert isinstance(h, HierarchicalData) and h.num_levels >= 2
    sizes = h.num_nodes_per_level()
    assert sizes[0] == num_nodes and all(a > b for a, b in zip(sizes, sizes[1:], strict=False))
    assert (
        torch.equal(h["l0"].x, data.x) and torch.equal(h["l0"].y, data.y) and torch.equal(h.scale, data.scale)
    )
    assert torch.equal(h["l0", "mesh", "l0"].edge_index, data.edge_index)  # the user's graph as given
    assert not any(rel == "contact" for _, rel, _ in h.edge_types)
    for k in range(h.num_levels):
        # coarse nodes are fine nodes: their positions are their roots'
        pos_k = h[f"l{k}"].pos
        assert torch.equal(pos_k, data.pos[h.fine_index(k)])
        relations = [("mesh", f"l{k}", f"l{k}")]
        if k + 1 < h.num_levels:
            relations += [("down", f"l{k}", f"l{k + 1}"), ("up", f"l{k + 1}", f"l{k}")]
        for rel, src, dst in relations:
            store = h[src, rel, dst]
            # by hand, edge by edge: x_i - x_j and its length
            j, i = store.edge_index.tolist()
            ps, pd = h[src].pos, h[dst].pos
            expected = [
                [*(pd[b] - ps[a]).tolist(), float((pd[b] - ps[a]).norm())] for a, b in zip(j, i, strict=True)
            ]
            assert store.edge_attr.shape == (len(j), 3)
            torch.testing.assert_close(store.edge_attr, torch.tensor(expected, dtype=torch.float64))


def test_initial_positions_and_given_edge_features_are_appended():
    data = random_mesh(400, seed=1)
    data.pos0 = data.pos + 0.01
    data.edge_attr = torch.arange(data.edge_index.size(1), dtype=torch.float64)  # [E]
    h = AMGHierarchy(max_levels=2, min_coarse_nodes=4)(data)
    mesh0, mesh1 = h["l0", "mesh", "l0"].edge_attr, h["l1", "mesh", "l1"].edge_attr
    assert mesh0.shape[1] == mesh1.shape[1] == 3 + 3 + 1
    torch.testing.assert_close(mesh0[:, 3:6], mesh0[:, :3])  # pos0 is pos moved rigidly
    assert torch.equal(mesh0[:, -1], data.edge_attr) and torch.equal(mesh1[:, -1], torch.zeros(len(mesh1)))
    assert torch.equal(h["l1"].pos0, data.pos0[h.fine_index(1)])


def test_component_radius_graph_on_a_plain_data_never_joins_a_component_to_itself():
    g = torch.Generator().manual_seed(3)
    pos = torch.rand(600, 2, generator=g, dtype=torch.float64)
    component = (pos[:, 0] > 0.5).long() + 2 * (pos[:, 1] > 0.5).long()  # four quadrants
    r, k = 0.08, 3
    data = ComponentRadiusGraph(r, k, edge_features=True)(Data(pos=pos, component=component))
    src, dst = data.contact_edge_index
    assert src.numel() > 0 and not (component[src] == component[dst]).any()
    assert set(zip(src.tolist(), dst.tolist(), strict=True)) == brute_force_contact(pos, component, r, k)
    torch.testing.assert_close(data.contact_edge_attr[:, :2], pos[dst] - pos[src])
    # carried on into the hierarchy as l0's contact relation (only: the coarse levels get none)
    mesh = FaceToEdge()(Delaunay()(data))
    h = AMGHierarchy(max_levels=2, min_coarse_nodes=4)(mesh)
    assert torch.equal(h["l0", "contact", "l0"].edge_index, data.contact_edge_index)
    assert ("l1", "contact", "l1") not in h.edge_types


def test_contact_edges_on_the_coarse_levels_of_a_plain_mesh_with_components():
    """AMGHierarchy, then ComponentRadiusGraph: each level's edges are a brute-force search over its nodes."""
    data = random_mesh(2000, seed=5)
    component = (data.pos[:, 0] > 0.5).long() + 2 * (data.pos[:, 1] > 0.5).long()  # four quadrants
    data.component = component
    h = AMGHierarchy(max_levels=3, min_coarse_nodes=4)(data)
    assert h.num_levels == 3
    r, k = 0.15, 2
    out = ComponentRadiusGraph(r, k)(h)
    fine = torch.arange(2000)  # the fine node of every node of the level, by the root maps
    for level in range(3):
        if level > 0:
            fine = fine[h[f"l{level}"].root]
        pos, comp = data.pos[fine], component[fine]
        assert torch.equal(h[f"l{level}"].pos, pos) and torch.equal(h[f"l{level}"].component, comp)
        src, dst = out[f"l{level}", "contact", f"l{level}"].edge_index
        assert src.numel() > 0 or level == 2
        assert set(zip(src.tolist(), dst.tolist(), strict=True)) == brute_force_contact(pos, comp, r, k)
        assert src.numel() == len(brute_force_contact(pos, comp, r, k))


def _two_meshes_with_three_and_two_levels() -> tuple[HierarchicalData, HierarchicalData]:
    transform = AMGHierarchy(max_levels=3, min_coarse_nodes=4)
    a, b = transform(random_mesh(2000, seed=0)), transform(random_mesh(60, seed=1))
    assert (a.num_levels, b.num_levels) == (3, 2)  # 2000 -> 200 -> 8 nodes; 60 -> 6 (-> fewer than 4)
    return a, b


def test_check_level_counts_finds_a_batch_of_hierarchies_with_different_level_counts():
    a, b = _two_meshes_with_three_and_two_levels()
    check_level_counts(a, 3)
    check_level_counts(b, 2)
    with pytest.raises(ValueError, match="the hierarchy has 2 levels, the model uses 3"):
        check_level_counts(b, 3)
    # PyG batches them silently: level l2 holds the 8 nodes of graph 0 only
    batch = Batch.from_data_list([a, b])
    assert batch.num_levels == 3 and batch["l2"].ptr.tolist() == [0, 8] and batch.num_graphs == 2
    check_level_counts(batch, 2)  # the levels the model uses are whole
    with pytest.raises(ValueError, match="1 of its 2 graphs have 2 levels, the model uses 3"):
        check_level_counts(batch, 3)
    # the first graph's levels are the batch's: the level l2 of graph 1 is left out
    with pytest.raises(ValueError, match="graph 0 has 2 levels, the model uses 3"):
        check_level_counts(Batch.from_data_list([b, a]), 3)
    loader = DataLoader([a, b, a, a], batch_size=4)
    with pytest.raises(
        ValueError, match=r"1 of its 4 graphs have 2 levels.*AMGHierarchy\(num_levels=\.\.\.\)"
    ):
        check_level_counts(next(iter(loader)), 3)
    check_level_counts(next(iter(DataLoader([a, a], batch_size=2))), 3)
    with pytest.raises(ValueError, match="num_levels must be an int >= 1"):
        check_level_counts(a, 0)


def test_amg_hierarchy_num_levels_gives_every_mesh_the_same_level_count():
    meshes = [random_mesh(n, seed=n) for n in (3000, 1500)]
    fixed = AMGHierarchy(max_levels=5, min_coarse_nodes=4, num_levels=3)  # max_levels is ignored
    free = AMGHierarchy(max_levels=5, min_coarse_nodes=4)
    hierarchies = [fixed(m) for m in meshes]
    for m, h in zip(meshes, hierarchies, strict=True):
        full = free(m)  # the same coarsening, cut after three levels
        assert h.num_levels == 3 and full.num_levels >= 3
        assert h.num_nodes_per_level() == full.num_nodes_per_level()[:3]
        assert torch.equal(h["l2"].root, full["l2"].root)
    assert AMGHierarchy(max_levels=5, min_coarse_nodes=4, num_levels=2)(meshes[0]).num_levels == 2
    batch = next(iter(DataLoader(hierarchies, batch_size=2)))
    check_level_counts(batch, 3)
    assert all(batch[f"l{k}"].ptr.numel() == 3 for k in range(3))
    small = random_mesh(300, seed=2)  # 300 -> 30 -> fewer than 4 nodes
    with pytest.raises(ValueError, match=r"num_levels=3\): the mesh of 300 nodes coarsens to 2 levels only"):
        fixed(small)
    assert AMGHierarchy(min_coarse_nodes=2, num_levels=3)(small).num_levels == 3
    assert "num_levels=3)" in repr(fixed)
    with pytest.raises(ValueError, match="num_levels must be an int >= 1"):
        AMGHierarchy(num_levels=0)


def test_a_batch_of_two_meshes_gives_the_two_single_outputs():
    transform = AMGHierarchy(max_levels=3, min_coarse_nodes=4)
    a, b = transform(random_mesh(2000, seed=0)), transform(random_mesh(1500, seed=1))
    assert a.num_levels == b.num_levels == 3
    torch.manual_seed(0)
    model = AMPN(5, 1, edge_channels=3, hidden_channels=16, mlp_channels=16, num_levels=3).double()
    batch = next(iter(DataLoader([a, b], batch_size=2)))
    model(batch)  # training mode: the input normalisers accumulate their statistics
    model.eval()  # then fixed, so that the three calls below see the same normalisation
    out = model(batch)  # [3500, 1]
    torch.testing.assert_close(out[:2000], model(a), rtol=0, atol=1e-12)
    torch.testing.assert_close(out[2000:], model(b), rtol=0, atol=1e-12)


def test_a_network_without_contact_relations_has_no_contact_parameters():
    mesh_only = AMPN(5, 1, edge_channels=3, hidden_channels=8, mlp_channels=8, num_levels=2)
    assert not [n for n, _ in mesh_only.named_parameters() if "contact" in n]
    both = AMPN(
        5, 1, edge_channels=3, hidden_channels=8, mlp_channels=8, num_levels=2, relations=("mesh", "contact")
    )
    assert [n for n, _ in both.named_parameters() if "contact" in n]
    with pytest.raises(ValueError, match=r"data\['l0'\].x must be \[N, 5\]"):
        mesh_only(AMGHierarchy(max_levels=2, min_coarse_nodes=4)(random_mesh(300, seed=0, features=4)))


@pytest.mark.parametrize("num_levels", [1, 2])
def test_ampn_trains_on_unstructured_meshes_of_several_sizes(num_levels):
    """Every parameter gets a gradient and 40 Adam steps take the error on the field down by half."""
    transform = AMGHierarchy(max_levels=2, min_coarse_nodes=4)
    meshes = [transform(random_mesh(n, seed=n)) for n in (500, 700, 900)]
    for h in meshes:
        h["l0"].x = torch.cat([h["l0"].x[:, :3], h["l0"].pos], 1).float()
        for store in h.edge_stores:
            store.edge_attr = store.edge_attr.float()
        h["l0"].y = h["l0"].y.float()
    loader = DataLoader(meshes, batch_size=3)
    torch.manual_seed(0)
    model = AMPN(5, 1, edge_channels=3, hidden_channels=16, mlp_channels=16, num_levels=num_levels)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = next(iter(loader))
    losses = []
    for step in range(40):
        optimizer.zero_grad()
        loss = (model(batch) - batch["l0"].y).square().mean()
        loss.backward()
        if step == 0:
            assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0], losses[::10]
