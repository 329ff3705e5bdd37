"""IntraLevelConv (eq. (1)) against a float64 dense-loop reference and PyG-style invariances."""

import pytest
import torch
from torch_geometric.nn.aggr import MaxAggregation, MeanAggregation, SoftmaxAggregation, SumAggregation

from torch_ampn.nn import IntraLevelConv
from torch_ampn.testing import (
    DEVICES,
    aggregate_reference,
    layer_norm_mlp_reference,
    random_intra_level_inputs,
)


def intra_ref(conv, x, mesh_index, e_mesh, contact_index, e_contact, aggr="max"):
    """Eq. (1) with explicit loops over edges and nodes, in float64."""
    x, e_mesh, e_contact = x.double(), e_mesh.double(), e_contact.double()
    n, d = x.shape

    def edges(index, e, lin, mlp):
        out = []
        for m in range(index.size(1)):
            j, i = int(index[0, m]), int(index[1, m])
            z = torch.cat([x[i], x[j], e[m]])
            out.append(lin.weight.double() @ e[m] + layer_norm_mlp_reference(mlp, z))
        return out

    new_c = edges(contact_index, e_contact, conv.lin_contact, conv.mlp_contact)
    new_m = edges(mesh_index, e_mesh, conv.lin_mesh, conv.mlp_mesh)
    x_new = []
    for i in range(n):
        in_c = [new_c[m] for m in range(len(new_c)) if int(contact_index[1, m]) == i]
        in_m = [new_m[m] for m in range(len(new_m)) if int(mesh_index[1, m]) == i]
        agg_c, agg_m = aggregate_reference(in_c, aggr, d), aggregate_reference(in_m, aggr, d)
        z = torch.cat([x[i], agg_c, agg_m])
        x_new.append(conv.lin_node.weight.double() @ x[i] + layer_norm_mlp_reference(conv.mlp_node, z))

    def stack(v):
        return torch.stack(v) if v else torch.zeros(0, d, dtype=torch.float64)

    return stack(x_new), stack(new_m), stack(new_c)


def graph(n=12, e=30, m=14, d=8, seed=0):
    return random_intra_level_inputs(n, e, m, d, seed)


def test_shapes_and_repr():
    conv = IntraLevelConv(8, mlp_channels=16)
    assert str(conv) == "IntraLevelConv(8, mlp_channels=16, aggr='max')"
    assert str(IntraLevelConv(8, aggr="mean")) == "IntraLevelConv(8, mlp_channels=128, aggr='mean')"
    x, mi, em, ci, ec = graph()
    out = conv(x, mi, em, ci, ec)
    assert [tuple(o.shape) for o in out] == [(12, 8), (30, 8), (14, 8)]
    with pytest.raises(ValueError, match="aggr"):
        IntraLevelConv(8, aggr="min")


@pytest.mark.parametrize("aggr", ["max", "sum", "mean"])
def test_matches_float64_reference(aggr):
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16, aggr=aggr)
    x, mi, em, ci, ec = graph(n=10, e=24, m=9)  # some nodes have no incoming contact edge
    assert len(set(ci[1].tolist())) < 10
    ref = intra_ref(conv, x, mi, em, ci, ec, aggr)
    out32 = conv(x, mi, em, ci, ec)
    for o, r in zip(out32, ref, strict=True):
        torch.testing.assert_close(o.double(), r, atol=1e-5, rtol=1e-5)
    out64 = conv.double()(x.double(), mi, em.double(), ci, ec.double())
    for o, r in zip(out64, ref, strict=True):
        torch.testing.assert_close(o, r, atol=1e-12, rtol=1e-12)


def test_empty_contact_set_aggregates_to_zero():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16).double()
    x, mi, em, _, _ = graph()
    x, em = x.double(), em.double()
    ci, ec = torch.empty(2, 0, dtype=torch.long), torch.empty(0, 8, dtype=torch.float64)
    out, _, e_c = conv(x, mi, em, ci, ec)
    assert e_c.shape == (0, 8) and torch.isfinite(out).all()
    torch.testing.assert_close(out, intra_ref(conv, x, mi, em, ci, ec)[0])


def test_node_permutation_equivariance():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16)
    x, mi, em, ci, ec = graph()
    perm = torch.randperm(12)
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(12)  # new index of old node
    out = conv(x, mi, em, ci, ec)
    out_p = conv(x[perm], inv[mi], em, inv[ci], ec)
    torch.testing.assert_close(out_p[0], out[0][perm])
    torch.testing.assert_close(out_p[1], out[1])
    torch.testing.assert_close(out_p[2], out[2])


def test_edge_order_invariance():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16)
    x, mi, em, ci, ec = graph()
    pm, pc = torch.randperm(mi.size(1)), torch.randperm(ci.size(1))
    out = conv(x, mi, em, ci, ec)
    out_p = conv(x, mi[:, pm], em[pm], ci[:, pc], ec[pc])
    torch.testing.assert_close(out_p[0], out[0])
    torch.testing.assert_close(out_p[1], out[1][pm])
    torch.testing.assert_close(out_p[2], out[2][pc])


def test_duplicate_edges_change_nothing_under_max():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16)
    x, mi, em, ci, ec = graph()
    dup_m, dup_c = torch.tensor([0, 3, 3]), torch.tensor([1, 5])
    out = conv(x, mi, em, ci, ec)
    out_d = conv(
        x,
        torch.cat([mi, mi[:, dup_m]], 1),
        torch.cat([em, em[dup_m]]),
        torch.cat([ci, ci[:, dup_c]], 1),
        torch.cat([ec, ec[dup_c]]),
    )
    torch.testing.assert_close(out_d[0], out[0])
    torch.testing.assert_close(out_d[1][30:], out[1][dup_m])
    # ... whereas a sum aggregation counts the copy twice:
    conv_sum = IntraLevelConv(8, mlp_channels=16, aggr="sum")
    a = conv_sum(x, mi, em, ci, ec)[0]
    b = conv_sum(x, torch.cat([mi, mi[:, dup_m]], 1), torch.cat([em, em[dup_m]]), ci, ec)[0]
    assert not torch.allclose(a, b)


@pytest.mark.parametrize("aggr", ["max", "sum"])
def test_output_depends_only_on_in_neighbourhood(aggr):
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16, aggr=aggr)
    x, mi, em, ci, ec = graph(n=20, e=25, m=10)
    out = conv(x, mi, em, ci, ec)[0]
    p = 7
    affected = {p} | {int(i) for j, i in torch.cat([mi, ci], 1).t() if int(j) == p}
    assert len(affected) > 2
    x2 = x.clone()
    x2[p] += 1.0
    out2 = conv(x2, mi, em, ci, ec)[0]
    changed = {i for i in range(20) if not torch.allclose(out[i], out2[i])}
    # A max may hide a changed message behind a larger one; a sum never does.
    assert p in changed and changed <= affected
    if aggr == "sum":
        assert changed == affected


def test_batch_of_two_graphs_equals_single_outputs():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16)
    g1, g2 = graph(n=12, seed=1), graph(n=9, e=20, m=7, seed=2)
    o1, o2 = conv(*g1), conv(*g2)
    x = torch.cat([g1[0], g2[0]])
    mi = torch.cat([g1[1], g2[1] + 12], 1)
    ci = torch.cat([g1[3], g2[3] + 12], 1)
    ob = conv(x, mi, torch.cat([g1[2], g2[2]]), ci, torch.cat([g1[4], g2[4]]))
    torch.testing.assert_close(ob[0], torch.cat([o1[0], o2[0]]))
    torch.testing.assert_close(ob[1], torch.cat([o1[1], o2[1]]))
    torch.testing.assert_close(ob[2], torch.cat([o1[2], o2[2]]))


@pytest.mark.parametrize("aggr", ["max", "sum", "mean", "softmax"])
@pytest.mark.parametrize("device", DEVICES)
def test_contact_mask_equals_dropping_edges(aggr, device):
    torch.manual_seed(0)
    if aggr == "softmax":  # a PyG Aggregation object with a learnable parameter
        aggr = SoftmaxAggregation(t=0.5, learn=True)
    conv = IntraLevelConv(8, mlp_channels=16, aggr=aggr).to(device)
    x, mi, em, ci, ec = (t.to(device) for t in graph(m=40))
    mask = torch.rand(40, device=device) > 0.5
    mask[ci[1] == ci[1, 0]] = False  # one node loses all its contact edges
    # Masked slots point anywhere valid (here at a node with large features).
    ci_table = torch.where(mask, ci, 0)
    x_big = x.clone()
    x_big[0] = 100.0
    out = conv(x_big, mi, em, ci_table, ec, mask)
    keep = torch.nonzero(mask).flatten()
    ref = conv(x_big, mi, em, ci[:, keep], ec[keep])
    torch.testing.assert_close(out[0], ref[0])
    torch.testing.assert_close(out[1], ref[1])
    torch.testing.assert_close(out[2][keep], ref[2])
    assert torch.all(out[2][~mask] == 0)


def test_bf16_autocast_runs_and_is_close_to_fp32():
    torch.manual_seed(0)
    conv = IntraLevelConv(16, mlp_channels=32)
    x, mi, em, ci, ec = graph(n=30, e=90, m=40, d=16)
    mask = torch.rand(40) > 0.3
    ref = conv(x, mi, em, ci, ec, mask)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conv(x, mi, em, ci, ec, mask)
    assert out[0].dtype == torch.bfloat16
    for o, r in zip(out, ref, strict=True):
        assert torch.isfinite(o).all()
        torch.testing.assert_close(o.float(), r, atol=0.1, rtol=0.05)


def test_gradients_and_reset_parameters():
    torch.manual_seed(0)
    conv = IntraLevelConv(8, mlp_channels=16)
    x, mi, em, ci, ec = graph()
    x.requires_grad_()
    out = conv(x, mi, em, ci, ec)
    sum(o.square().sum() for o in out).backward()
    assert x.grad is not None
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in conv.parameters())
    with torch.no_grad():
        for p in conv.parameters():
            p.fill_(7.0)
    conv.reset_parameters()
    assert all(not torch.all(p == 7.0) for p in conv.parameters())


@pytest.mark.parametrize(
    "name, aggregation", [("max", MaxAggregation()), ("sum", SumAggregation()), ("mean", MeanAggregation())]
)
def test_aggregation_objects_equal_their_names(name, aggregation):
    args = graph(m=30)
    torch.manual_seed(0)
    by_name = IntraLevelConv(8, mlp_channels=16, aggr=name)
    torch.manual_seed(0)
    by_object = IntraLevelConv(8, mlp_channels=16, aggr=aggregation)
    for a, b in zip(by_name(*args), by_object(*args), strict=True):
        assert torch.equal(a, b)
    assert str(by_object) == "IntraLevelConv(8, mlp_channels=16, aggr='" + type(aggregation).__name__ + "()')"
    with pytest.raises(ValueError, match="aggr must be one of"):
        IntraLevelConv(8, aggr="median")


def test_learnable_aggregation_gets_a_gradient_against_a_float64_reference():
    """SoftmaxAggregation: sum_j softmax_j(t e_j) e_j per channel, by hand in float64."""
    torch.manual_seed(0)
    conv = IntraLevelConv(4, mlp_channels=8, aggr=SoftmaxAggregation(t=2.0, learn=True)).double()
    x, mi, em, ci, ec = (t.double() if t.is_floating_point() else t for t in graph(n=6, d=4, e=9, m=5))
    _, e_mesh, _ = conv(x, mi, em, ci, ec)
    agg = conv.propagate(mi, edge_attr=e_mesh, size=(6, 6))
    for i in range(6):
        incoming = e_mesh[mi[1] == i]
        expected = torch.zeros(4, dtype=torch.float64)
        if len(incoming):
            w = torch.softmax(2.0 * incoming, dim=0)
            expected = (w * incoming).sum(0)
        torch.testing.assert_close(agg[i], expected)
    conv(x, mi, em, ci, ec)[0].sum().backward()
    assert conv.aggr_module.t.grad is not None and conv.aggr_module.t.grad != 0
