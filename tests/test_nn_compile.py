"""torch.compile: zero graph breaks (dynamo.explain) and compiled == eager outputs."""

import pytest
import torch

from torch_ampn.forming import ampn_channels, hierarchical_features
from torch_ampn.nn import InterLevelConv, IntraLevelConv
from torch_ampn.nn import RobinAMPN as AMPN
from torch_ampn.testing import random_inter_level_inputs, random_intra_level_inputs, toy_hierarchy


@pytest.fixture(autouse=True)
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def intra_inputs():
    return random_intra_level_inputs(
        num_nodes=20, num_mesh_edges=60, num_contact_edges=30, channels=16, mask_drop_prob=0.3
    )


@pytest.fixture(scope="module")
def toy():
    h = toy_hierarchy(nx=6, ny=5, max_levels=3)
    x_dict, e_dict = hierarchical_features(h, 3)
    masks = {k: torch.rand(v.size(1)) > 0.2 for k, v in h.edge_index_dict.items() if k[1] == "contact"}
    return h, x_dict, e_dict, masks


@pytest.mark.parametrize("masked", [False, True])
def test_intra_level_conv_has_no_graph_breaks(masked):
    conv = IntraLevelConv(16, mlp_channels=32)
    args = intra_inputs()
    args = args if masked else args[:-1]
    explanation = torch._dynamo.explain(conv)(*args)
    assert explanation.graph_break_count == 0 and explanation.graph_count == 1


def test_inter_level_conv_has_no_graph_breaks():
    conv = InterLevelConv(16, mlp_channels=32)
    x_src, x_dst, edge_index, e = random_inter_level_inputs(num_src=20, num_dst=6, num_edges=30, channels=16)
    explanation = torch._dynamo.explain(conv)((x_src, x_dst), edge_index, e)
    assert explanation.graph_break_count == 0 and explanation.graph_count == 1


def test_ampn_has_no_graph_breaks(toy):
    h, x_dict, e_dict, masks = toy
    model = AMPN(
        **ampn_channels(3, 2), hidden_channels=16, num_levels=3, num_step_frequencies=2, noise_channels=3
    )
    noise = torch.randn(h["l0"].num_nodes, 3)
    explanation = torch._dynamo.explain(model)(
        x_dict, h.edge_index_dict, e_dict, noise=noise, step=torch.tensor(1), contact_mask_dict=masks
    )
    assert explanation.graph_break_count == 0 and explanation.graph_count == 1


@pytest.mark.slow
@pytest.mark.usefixtures("unoptimised_kernels")
def test_compiled_layer_gradients_match_eager_on_two_sizes():
    """The training step's compile (Inductor, forward and backward, ``dynamic=True``) on one
    message-passing layer (InterLevelConv: an edge and a node MLP, scatter aggregation): input
    and parameter gradients equal eager's on two graph sizes, from one compiled graph."""
    torch.manual_seed(0)
    conv = InterLevelConv(16, mlp_channels=32)
    compiled = torch.compile(conv, dynamic=True)
    for num_src, num_dst, num_edges in ((20, 6, 30), (27, 9, 41)):
        x_src, x_dst, edge_index, e = random_inter_level_inputs(num_src, num_dst, num_edges, channels=16)
        grads = []
        for model in (conv, compiled):
            x = x_src.clone().requires_grad_()
            out = model((x, x_dst), edge_index, e)
            loss = sum((o * torch.linspace(-1, 1, o.numel()).view_as(o)).sum() for o in out)
            grads.append(torch.autograd.grad(loss, [x, *conv.parameters()]))
        for g_comp, g_eager in zip(grads[1], grads[0], strict=True):
            torch.testing.assert_close(g_comp, g_eager, atol=1e-4, rtol=1e-4)


@pytest.mark.usefixtures("unoptimised_kernels")
def test_compiled_intra_level_conv_matches_eager():
    torch.manual_seed(0)
    conv = IntraLevelConv(16, mlp_channels=32)
    args = intra_inputs()
    expected = conv(*args)
    compiled = torch.compile(conv)
    for out, ref in zip(compiled(*args), expected, strict=True):
        torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)


@pytest.mark.slow
@pytest.mark.usefixtures("unoptimised_kernels")
def test_compiled_ampn_matches_eager(toy):
    """A 2-level V-cycle of one layer of each kind (Down, Solve with contact edges, Up): a
    fraction of the paper net's compile (Pre and Post are Solve's kind of layer on another level).

    Inference (no autograd graph), as the fast rollout compiles it; the compiled training step
    has its own test (tests/test_training.py)."""
    h, x_dict, e_dict, masks = toy
    torch.manual_seed(0)
    layers = dict(pre_layers=0, down_layers=1, solve_layers=1, post_layers=0, up_layers=1)
    model = AMPN(**ampn_channels(3, 2), hidden_channels=16, num_levels=2, noise_channels=3, **layers)
    noise = torch.randn(h["l0"].num_nodes, 3)
    with torch.no_grad():
        expected = model(x_dict, h.edge_index_dict, e_dict, noise=noise, contact_mask_dict=masks)
        out = torch.compile(model)(x_dict, h.edge_index_dict, e_dict, noise=noise, contact_mask_dict=masks)
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=1e-5)
