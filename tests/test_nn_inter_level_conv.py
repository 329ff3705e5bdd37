"""InterLevelConv (eq. (2)) against a float64 dense-loop reference and PyG-style invariances."""

import pytest
import torch

from torch_ampn.nn import InterLevelConv
from torch_ampn.testing import aggregate_reference, layer_norm_mlp_reference, random_inter_level_inputs


def inter_ref(conv, x_src, x_dst, edge_index, e, aggr="max"):
    """Eq. (2) with explicit loops: receivers i = edge_index[1] (targets), senders j = edge_index[0]."""
    x_src, x_dst, e = x_src.double(), x_dst.double(), e.double()
    d = x_dst.size(1)
    new_e = []
    for m in range(edge_index.size(1)):
        j, i = int(edge_index[0, m]), int(edge_index[1, m])
        z = torch.cat([x_dst[i], x_src[j], e[m]])
        new_e.append(conv.lin_edge.weight.double() @ e[m] + layer_norm_mlp_reference(conv.mlp_edge, z))
    out = []
    for i in range(x_dst.size(0)):
        inc = [new_e[m] for m in range(len(new_e)) if int(edge_index[1, m]) == i]
        agg = aggregate_reference(inc, aggr, d)
        z = torch.cat([x_dst[i], agg])
        out.append(conv.lin_node.weight.double() @ x_dst[i] + layer_norm_mlp_reference(conv.mlp_node, z))
    return torch.stack(out), torch.stack(new_e)


def bipartite(n_src=15, n_dst=6, e=24, d=8, seed=0):
    return random_inter_level_inputs(n_src, n_dst, e, d, seed)


def test_shapes_and_repr():
    conv = InterLevelConv(8, mlp_channels=16)
    assert str(conv) == "InterLevelConv(8, mlp_channels=16, aggr='max')"
    xs, xd, ei, e = bipartite()
    out, e_new = conv((xs, xd), ei, e)
    assert out.shape == (6, 8) and e_new.shape == (24, 8)


@pytest.mark.parametrize("aggr", ["max", "sum", "mean"])
def test_matches_float64_reference(aggr):
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16, aggr=aggr)
    xs, xd, ei, e = bipartite(n_dst=10, e=12)  # some receivers get nothing
    assert len(set(ei[1].tolist())) < 10
    ref = inter_ref(conv, xs, xd, ei, e, aggr)
    for o, r in zip(conv((xs, xd), ei, e), ref, strict=True):
        torch.testing.assert_close(o.double(), r, atol=1e-5, rtol=1e-5)
    conv = conv.double()
    for o, r in zip(conv((xs.double(), xd.double()), ei, e.double()), ref, strict=True):
        torch.testing.assert_close(o, r, atol=1e-12, rtol=1e-12)


def test_down_and_up_directions():
    """Down: fine sources -> coarse targets; up: the reversed edges update the fine nodes."""
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16)
    fine, coarse, down, e = bipartite(n_src=15, n_dst=6)
    x_coarse, _ = conv((fine, coarse), down, e)
    assert x_coarse.shape == coarse.shape
    x_fine, _ = conv((coarse, fine), down.flip(0), e)
    assert x_fine.shape == fine.shape
    ref = inter_ref(conv, coarse, fine, down.flip(0), e)[0]
    conv = conv.double()
    x_fine64, _ = conv((coarse.double(), fine.double()), down.flip(0), e.double())
    torch.testing.assert_close(x_fine64, ref, atol=1e-12, rtol=1e-12)


def test_permutation_equivariance_of_both_node_sets():
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16)
    xs, xd, ei, e = bipartite()
    ps, pd = torch.randperm(15), torch.randperm(6)
    inv_s, inv_d = torch.argsort(ps), torch.argsort(pd)
    out, e_new = conv((xs, xd), ei, e)
    out_p, e_p = conv((xs[ps], xd[pd]), torch.stack([inv_s[ei[0]], inv_d[ei[1]]]), e)
    torch.testing.assert_close(out_p, out[pd])
    torch.testing.assert_close(e_p, e_new)


def test_edge_order_invariance_and_duplicates():
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16)
    xs, xd, ei, e = bipartite()
    out, e_new = conv((xs, xd), ei, e)
    perm = torch.randperm(24)
    out_p, e_p = conv((xs, xd), ei[:, perm], e[perm])
    torch.testing.assert_close(out_p, out)
    torch.testing.assert_close(e_p, e_new[perm])
    dup = torch.tensor([2, 2, 9])
    out_d, _ = conv((xs, xd), torch.cat([ei, ei[:, dup]], 1), torch.cat([e, e[dup]]))
    torch.testing.assert_close(out_d, out)


def test_receiver_depends_only_on_its_senders():
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16, aggr="sum")
    xs, xd, ei, e = bipartite(n_src=20, n_dst=8, e=16)
    out, _ = conv((xs, xd), ei, e)
    p = int(ei[0, 0])
    affected = {int(i) for j, i in ei.t() if int(j) == p}
    xs2 = xs.clone()
    xs2[p] += 1.0
    out2, _ = conv((xs2, xd), ei, e)
    changed = {i for i in range(8) if not torch.allclose(out[i], out2[i])}
    assert changed == affected


def test_batch_of_two_graphs_equals_single_outputs():
    torch.manual_seed(0)
    conv = InterLevelConv(8, mlp_channels=16)
    a, b = bipartite(seed=1), bipartite(n_src=11, n_dst=4, e=13, seed=2)
    oa, ob = conv((a[0], a[1]), a[2], a[3]), conv((b[0], b[1]), b[2], b[3])
    ei = torch.cat([a[2], b[2] + torch.tensor([[15], [6]])], 1)
    out, e_new = conv((torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]])), ei, torch.cat([a[3], b[3]]))
    torch.testing.assert_close(out, torch.cat([oa[0], ob[0]]))
    torch.testing.assert_close(e_new, torch.cat([oa[1], ob[1]]))


def test_bf16_autocast_runs_and_is_close_to_fp32():
    torch.manual_seed(0)
    conv = InterLevelConv(16, mlp_channels=32)
    xs, xd, ei, e = bipartite(n_src=40, n_dst=10, e=60, d=16)
    ref = conv((xs, xd), ei, e)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conv((xs, xd), ei, e)
    for o, r in zip(out, ref, strict=True):
        assert torch.isfinite(o).all()
        torch.testing.assert_close(o.float(), r, atol=0.1, rtol=0.05)


def test_reset_parameters_resets_every_submodule():
    conv = InterLevelConv(8, mlp_channels=16)
    with torch.no_grad():
        for p in conv.parameters():
            p.fill_(7.0)
    conv.reset_parameters()
    assert all(not torch.all(p == 7.0) for p in conv.parameters())
