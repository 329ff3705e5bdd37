"""Feature builders against hand-computed values; batching; the hierarchy helper."""

import math

import torch
from torch_geometric.data import Batch

from torch_ampn.data import NodeType
from torch_ampn.forming import (
    coarse_node_features,
    edge_features,
    fine_node_features,
    gripper_features,
    hierarchical_features,
    num_edge_features,
    num_fine_node_features,
)
from torch_ampn.testing import toy_hierarchy


def test_gripper_features_hand_computed():
    pos = torch.tensor([[3.0, 4.0, 0.0]], dtype=torch.float64)
    g = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 12.0]], dtype=torch.float64)
    f = torch.tensor([[10.0, 0.0, 0.0], [0.0, 0.0, 5.0]], dtype=torch.float64)
    out = gripper_features(pos, g, f, alpha=0.03, eps=1e-8)
    w1, w2 = math.exp(-0.03 * 5), math.exp(-0.03 * 12)
    # gripper 1: d = (3, 4, 0), |d| = 5, f.d_hat = 6 -> projected force 6 * (0.6, 0.8, 0)
    # gripper 2: d = (0, 0, -12), |d| = 12, f.d_hat = -5 -> projected force -5 * (0, 0, -1)
    expected = [3, 4, 0, 5, 0.6, 0.8, 0]
    expected += [0, 0, -12, 12, 0, 0, -1]
    expected += [3.6 * w1, 4.8 * w1, 5 * w2]  # f_proj_weighted
    expected += [10 * w1, 0, 5 * w2, math.sqrt(100 * w1**2 + 25 * w2**2)]  # f_weighted, |f_weighted|
    torch.testing.assert_close(out[0], torch.tensor(expected, dtype=torch.float64), atol=1e-7, rtol=1e-7)


def test_gripper_features_at_the_gripper_are_finite():
    pos = torch.zeros(1, 3)
    out = gripper_features(pos, torch.zeros(1, 3), torch.ones(1, 3))
    assert torch.isfinite(out).all() and torch.all(out[0, 4:7] == 0)


def test_gripper_features_per_graph_with_batch_vector():
    g = torch.Generator().manual_seed(0)
    pos = torch.randn(7, 3, generator=g)
    grip_pos, grip_force = torch.randn(2, 3, 3, generator=g), torch.randn(2, 3, 3, generator=g)
    batch = torch.tensor([0, 0, 0, 1, 1, 1, 1])
    out = gripper_features(pos, grip_pos, grip_force, batch)
    assert out.shape == (7, 7 * 3 + 7)
    torch.testing.assert_close(out[:3], gripper_features(pos[:3], grip_pos[0], grip_force[0]))
    torch.testing.assert_close(out[3:], gripper_features(pos[3:], grip_pos[1:], grip_force[1:]))


def test_fine_node_features_layout():
    n, c, num_grippers = 5, 4, 2
    node_type = torch.tensor([0, 0, 1, 2, 0])
    prev, bc, fiber = torch.randn(n, 3), torch.randn(n, 3), torch.randn(n, 3)
    component = torch.tensor([0, 1, 2, 3, 1])
    pos = torch.randn(n, 3)
    gp, gf = torch.randn(num_grippers, 3), torch.randn(num_grippers, 3)
    x = fine_node_features(node_type, prev, bc, fiber, component, c, gripper_features(pos, gp, gf))
    assert x.shape == (n, num_fine_node_features(c, num_grippers))
    t = NodeType.count()
    assert torch.equal(x[:, :t].argmax(1), node_type) and torch.all(x[:, :t].sum(1) == 1)
    assert torch.equal(x[:, t : t + 3], prev) and torch.equal(x[:, t + 3 : t + 6], bc)
    assert torch.equal(x[:, t + 6 : t + 9], fiber)
    assert torch.equal(x[:, t + 9 : t + 9 + c].argmax(1), component)
    assert torch.equal(x[:, t + 9 + c :], gripper_features(pos, gp, gf))
    assert torch.equal(coarse_node_features(node_type), x[:, :t])


def test_edge_features_hand_computed():
    pos = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    pos0 = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    ei = torch.tensor([[0], [1]])  # source 0 -> target 1: x_i - x_j = pos[1] - pos[0]
    assert edge_features(ei, pos, pos).tolist() == [[3.0, 4.0, 0.0, 5.0]]
    assert edge_features(ei, pos, pos, pos0, pos0).tolist() == [[3.0, 4.0, 0.0, 5.0, 0.0, 0.0, 2.0, 2.0]]
    # bipartite: sources and targets from different node sets
    coarse = torch.tensor([[1.0, 1.0, 1.0]])
    out = edge_features(torch.tensor([[1], [0]]), pos, coarse)
    torch.testing.assert_close(out, torch.tensor([[-2.0, -3.0, 1.0, math.sqrt(14.0)]]))


def test_hierarchical_features_shapes_and_roots():
    h = toy_hierarchy(nx=6, ny=5, num_components=3, max_levels=3)
    x_dict, e_dict = hierarchical_features(h, num_components=3)
    assert set(x_dict) == set(h.node_types)
    assert x_dict["l0"].shape == (h["l0"].num_nodes, num_fine_node_features(3, 2))
    for k in range(1, h.num_levels):
        idx = h.fine_index(k)
        assert torch.equal(x_dict[f"l{k}"].argmax(1), h["l0"].node_type[idx])
    assert set(e_dict) == set(h.edge_types)
    for (src, rel, dst), e in e_dict.items():
        ei = h[src, rel, dst].edge_index
        assert e.shape == (ei.size(1), num_edge_features(rel))
        # current relative position of the edge from the root fine nodes' positions
        ps, pd = h["l0"].pos[h.fine_index(int(src[1:]))], h["l0"].pos[h.fine_index(int(dst[1:]))]
        torch.testing.assert_close(e[:, :3], pd[ei[1]] - ps[ei[0]])


def test_hierarchical_features_of_a_batch_equal_the_single_ones():
    a = toy_hierarchy(nx=6, ny=5, seed=1)
    b = toy_hierarchy(nx=5, ny=4, seed=2)
    batch = Batch.from_data_list([a, b])
    xa, ea = hierarchical_features(a, 3)
    xb, eb = hierarchical_features(b, 3)
    x, e = hierarchical_features(batch, 3)
    for k in x:
        torch.testing.assert_close(x[k], torch.cat([xa[k], xb[k]]))
    for k in e:
        torch.testing.assert_close(e[k], torch.cat([ea[k], eb[k]]))
