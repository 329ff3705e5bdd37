"""AMPN's multigrid options (prolongator-weighted transfers, restricted coarse inputs, online
normalisation) and the weighted-mean transfer, against dense float64 references."""

from __future__ import annotations

import pytest
import torch
from torch_geometric.data import Batch

from torch_ampn.datasets import laplace_sample
from torch_ampn.hierarchy import edge_type
from torch_ampn.nn import AMPN, InterLevelConv, weighted_mean
from torch_ampn.transforms import AMGHierarchy


@pytest.fixture(scope="module")
def mesh():
    return AMGHierarchy(max_levels=3, min_coarse_nodes=4)(laplace_sample(600, seed=0))


def test_weighted_mean_by_hand():
    # target 0: (2 [1, 2] + 1 [4, 8]) / 3; target 1: -0.5 [3, 3] / -0.5; target 2: no edge
    ei = torch.tensor([[0, 1, 2], [0, 0, 1]])
    e = torch.tensor([[1.0, 2.0], [4.0, 8.0], [3.0, 3.0]])
    w = torch.tensor([2.0, 1.0, -0.5])
    out = weighted_mean(ei, e, w, 3)
    torch.testing.assert_close(out, torch.tensor([[2.0, 4.0], [3.0, 3.0], [0.0, 0.0]]))


def test_inter_level_conv_with_weights_ignores_zero_weight_edges():
    torch.manual_seed(0)
    conv = InterLevelConv(8, 16, aggr="max").double()
    x_src, x_dst = torch.randn(4, 8, dtype=torch.float64), torch.randn(2, 8, dtype=torch.float64)
    ei = torch.tensor([[0, 1, 2, 3], [0, 0, 1, 1]])
    e = torch.randn(4, 8, dtype=torch.float64)
    w = torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    out, _ = conv((x_src, x_dst), ei, e, w)
    # with one edge of weight 1 per target the weighted mean is that edge's message: any aggregation
    kept = torch.tensor([0, 3])
    expected, _ = conv((x_src, x_dst), ei[:, kept], e[kept])
    torch.testing.assert_close(out, expected)


def test_restricted_coarse_inputs_equal_the_dense_restriction(mesh):
    model = AMPN(
        4, 1, 3, hidden_channels=8, mlp_channels=8, num_levels=3, coarse_inputs="restrict", normalize=False
    ).double()  # raw inputs restricted (normalised ones would be: the normalisation runs first)
    seen = []
    model.node_encoders["coarse"].register_forward_hook(lambda m, args, out: seen.append(args[0]))
    h = mesh.clone()
    for store in h.stores:
        for key, value in store.items():
            if torch.is_tensor(value) and value.is_floating_point():
                store[key] = value.double()
    model(h)
    x = h["l0"].x  # [N, 4]
    for k in (1, 2):
        store = h[edge_type("down", k - 1)]
        n_f, n_c = h[f"l{k - 1}"].num_nodes, h[f"l{k}"].num_nodes
        P = torch.zeros(n_f, n_c, dtype=torch.float64)
        P[store.edge_index[0], store.edge_index[1]] = store.edge_weight.double().abs()
        x = (P.t() @ x) / P.sum(0, keepdim=True).t()  # the |P|-weighted mean over each aggregate
        restricted = seen[k - 1][:, :4]  # [N_k, 4], then the level encoding
        torch.testing.assert_close(restricted, x)


def test_transfer_weights_need_the_prolongator_weights(mesh):
    model = AMPN(4, 1, 3, hidden_channels=8, mlp_channels=8, num_levels=3, transfer_weights=True)
    h = mesh.clone()
    del h[edge_type("down", 0)].edge_weight
    with pytest.raises(ValueError, match="edge_weight"):
        model(h)
    assert model(mesh).shape == (mesh["l0"].num_nodes, 1)


def test_online_normalisation_accumulates_the_training_batches_then_freezes(mesh):
    sizes = dict(hidden_channels=8, mlp_channels=8, num_levels=3)
    model = AMPN(4, 1, 3, **sizes, normalize=True, normalize_batches=2)
    other = AMGHierarchy(max_levels=3, min_coarse_nodes=4)(laplace_sample(500, seed=1))
    model.eval()
    model(mesh)  # evaluation: no statistics
    assert int(model.normalized_batches) == 0
    model.train()
    model(mesh)
    model(other)
    model(mesh)  # beyond normalize_batches: frozen
    assert int(model.normalized_batches) == 2
    x = torch.cat([mesh["l0"].x, other["l0"].x]).double()
    torch.testing.assert_close(model.node_norm["fine"].mean, x.mean(0))
    torch.testing.assert_close(model.node_norm["fine"].std, x.std(0, unbiased=False))
    for k, rel in ((0, "mesh"), (1, "mesh"), (1, "up"), (0, "down")):
        key = edge_type(rel, k)
        e = torch.cat([mesh[key].edge_attr, other[key].edge_attr]).double()
        torch.testing.assert_close(model.edge_norm[f"{rel}{k}"].std, e.std(0, unbiased=False))
    state = {k: v.clone() for k, v in model.state_dict().items()}
    copy = AMPN(4, 1, 3, **sizes, normalize=True, normalize_batches=2)
    copy.load_state_dict(state)
    copy.eval(), model.eval()
    torch.testing.assert_close(copy(mesh), model(mesh))  # the statistics travel in the state dict


def test_a_batch_of_hierarchies_with_fewer_levels_is_refused_before_any_computation():
    small = AMGHierarchy(max_levels=2, min_coarse_nodes=4)(laplace_sample(300, seed=2))
    big = AMGHierarchy(max_levels=3, min_coarse_nodes=4)(laplace_sample(600, seed=3))
    model = AMPN(4, 1, 3, hidden_channels=8, mlp_channels=8, num_levels=3)
    with pytest.raises(ValueError, match="levels"):
        model(Batch.from_data_list([big, small]))


def test_triangles_travel_on_l0_and_batch_with_offsets():
    to_hierarchy = AMGHierarchy(num_levels=3, min_coarse_nodes=4)
    a, b = to_hierarchy(laplace_sample(500, seed=4)), to_hierarchy(laplace_sample(500, seed=5))
    batch = Batch.from_data_list([a, b])
    na, ta = a["l0"].num_nodes, a["l0"].face.size(1)
    assert torch.equal(batch["l0"].face[:, :ta], a["l0"].face)
    assert torch.equal(batch["l0"].face[:, ta:], b["l0"].face + na)  # offset like a PyG Data's faces
    assert torch.equal(batch.get_example(1)["l0"].face, b["l0"].face)


def test_normalisation_reaches_the_network_and_leaves_the_input_alone(mesh):
    # the same weights, once normalising inside, once fed inputs standardised by hand
    torch.manual_seed(0)
    sizes = dict(hidden_channels=8, mlp_channels=8, num_levels=3)
    inside = AMPN(4, 1, 3, **sizes, normalize=True, normalize_batches=1).double()
    plain = AMPN(4, 1, 3, **sizes).double()
    plain.load_state_dict({k: v for k, v in inside.state_dict().items() if k in plain.state_dict()})
    h = mesh.clone()
    for store in h.stores:
        for key, value in store.items():
            if torch.is_tensor(value) and value.is_floating_point():
                store[key] = value.double()
    inside.train()
    inside(h)  # accumulates the statistics of this one batch, then frozen
    inside.eval()
    x_before = h["l0"].x.clone()
    out = inside(h)
    assert torch.equal(h["l0"].x, x_before)  # the caller's data is not changed
    scaled = h.clone()
    scaled["l0"].x = (h["l0"].x - h["l0"].x.mean(0)) / h["l0"].x.std(0, unbiased=False)
    for key in scaled.edge_types:
        e = h[key].edge_attr
        scaled[key].edge_attr = (e - e.mean(0)) / e.std(0, unbiased=False)
    torch.testing.assert_close(out, plain.eval()(scaled))
    assert not torch.allclose(out, plain(h))  # and normalising changes the result
