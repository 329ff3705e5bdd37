"""AMPN: shapes, the V-cycle schedule, shared weights, parameter count, gradients, batching, I/O."""

import io

import pytest
import torch
from torch_geometric.data import Batch

from torch_ampn.forming import ampn_channels, hierarchical_features
from torch_ampn.nn import RobinAMPN as AMPN
from torch_ampn.testing import count_parameters, toy_hierarchy

C, G = 3, 2  # components and grippers of the toy hierarchy
SIZES = ampn_channels(C, G)  # fine, coarse and edge input widths
F0 = SIZES["fine_in_channels"]


@pytest.fixture(scope="module")
def toy():
    h = toy_hierarchy(nx=10, ny=8, num_components=C, max_levels=4, num_grippers=G)
    assert h.num_levels == 4
    x_dict, e_dict = hierarchical_features(h, C)
    return h, x_dict, e_dict


@pytest.fixture(scope="module")
def toy3():
    """Three levels; unlike ``toy``'s, its coarsest level has mesh edges (so Solve gets gradients)."""
    h = toy_hierarchy(nx=14, ny=12, num_components=C, max_levels=3, num_grippers=G, min_coarse_nodes=4)
    assert h.num_levels == 3 and h.mesh(2).edge_index.size(1) > 0
    x_dict, e_dict = hierarchical_features(h, C)
    return h, x_dict, e_dict


def make(num_levels=3, d=16, **kwargs):
    torch.manual_seed(0)
    kwargs.setdefault("noise_channels", 3)
    return AMPN(**SIZES, hidden_channels=d, num_levels=num_levels, **kwargs)


def noise_for(h, seed=0):
    return torch.randn(h["l0"].num_nodes, 3, generator=torch.Generator().manual_seed(seed))


def expected_parameter_count(d, h, num_levels, f0=F0, fc=3, level_freq=4, noise=3, out=3):
    """Parameters counted from the paper's description, independently of the implementation."""
    linear = lambda i, o, bias=True: i * o + (o if bias else 0)  # noqa: E731
    mlp = lambda i, o: 2 * i + linear(i, h) + linear(h, o)  # noqa: E731  LayerNorm + 2 Linear
    intra = 3 * linear(d, d, bias=False) + 2 * mlp(3 * d, d) + mlp(3 * d, d)  # W_C, W_M, W_V; f_C, f_M, f_V
    inter = 2 * linear(d, d, bias=False) + mlp(3 * d, d) + mlp(2 * d, d)  # W_E, W_V; f_E, f_V
    pre, down, solve, post, up = 3, 2, 5, 3, 2
    cond = 2 * level_freq
    total = linear(f0 + noise + cond, d) + linear(8, d) + linear(4, d) + linear(d, out)
    total += (pre + solve + post) * intra
    if num_levels > 1:
        total += linear(fc + cond, d) + 2 * linear(8, d) + (down + up) * inter
    return total


def test_output_shape_and_defaults(toy):
    h, x_dict, e_dict = toy
    model = make()
    assert model.num_layers == 15
    out = model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h))
    assert out.shape == (h["l0"].num_nodes, 3) and torch.isfinite(out).all()
    paper = AMPN(**SIZES)
    assert (paper.hidden_channels, paper.mlp_channels, paper.num_levels, paper.aggr) == (128, 128, 4, "max")
    assert paper.noise_channels == 0
    assert paper.pre[0].mlp_channels == 128 and paper.num_layers == 15
    assert "num_levels=4" in str(paper)


@pytest.mark.parametrize("num_levels", [1, 2, 3, 4])
def test_parameter_count_is_the_15_shared_layers(num_levels):
    model = make(num_levels, d=16, mlp_channels=24)
    assert count_parameters(model) == expected_parameter_count(16, 24, num_levels)
    if num_levels > 1:
        assert count_parameters(model) == count_parameters(make(2, d=16, mlp_channels=24))
    else:
        assert len(model.down) == len(model.up) == 0 and "coarse" not in model.node_encoders


def test_v_cycle_schedule_and_weight_sharing(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=4)
    calls = []
    for name in ("pre", "down", "solve", "post", "up"):
        for i, conv in enumerate(getattr(model, name)):
            conv.register_forward_hook(
                lambda m, args, out, name=name, i=i: calls.append((name, i, out[0].size(0)))
            )
    model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h))
    n = h.num_nodes_per_level()
    first = [(name, size) for name, i, size in calls if i == 0]
    assert first == [
        ("pre", n[0]), ("down", n[1]),
        ("pre", n[1]), ("down", n[2]),
        ("pre", n[2]), ("down", n[3]),
        ("pre", n[3]), ("solve", n[3]), ("post", n[3]),
        ("up", n[2]), ("post", n[2]),
        ("up", n[1]), ("post", n[1]),
        ("up", n[0]), ("post", n[0]),
    ]  # fmt: skip
    assert len(calls) == 4 * 3 + 3 * 2 + 5 + 4 * 3 + 3 * 2  # shared stacks run on every level


def test_flat_baseline_runs_pre_solve_post_on_l0_only(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=1)
    sizes = []
    for stack in (model.pre, model.solve, model.post):
        for conv in stack:
            conv.register_forward_hook(lambda m, args, out: sizes.append(out[0].size(0)))
    out = model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h))  # coarser levels ignored
    assert out.shape == (h["l0"].num_nodes, 3) and sizes == [h["l0"].num_nodes] * 11


def test_too_few_levels_in_the_input_raises(toy):
    h, x_dict, e_dict = toy
    with pytest.raises(KeyError, match="l4"):
        make(num_levels=5)(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h))


@pytest.mark.parametrize("num_levels", [1, 3])
def test_gradient_reaches_every_parameter(toy3, num_levels):
    h, x_dict, e_dict = toy3
    model = make(num_levels)
    model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h)).square().mean().backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert missing == []


def test_state_dict_round_trip_gives_identical_outputs(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=4).eval()
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    buf.seek(0)
    torch.manual_seed(123)
    other = AMPN(**SIZES, hidden_channels=16, num_levels=4, noise_channels=3).eval()
    other.load_state_dict(torch.load(buf, weights_only=True))
    noise = noise_for(h)
    a = model(x_dict, h.edge_index_dict, e_dict, noise=noise)
    b = other(x_dict, h.edge_index_dict, e_dict, noise=noise)
    assert torch.equal(a, b)


def test_no_noise_input_by_default_and_a_declared_one_must_be_given(toy):
    h, x_dict, e_dict = toy
    torch.manual_seed(0)
    plain = AMPN(**SIZES, hidden_channels=16, num_levels=3).eval()
    a = plain(x_dict, h.edge_index_dict, e_dict)
    assert torch.isfinite(a).all() and torch.equal(a, plain(x_dict, h.edge_index_dict, e_dict))
    assert plain.node_encoders["fine"].in_features == F0 + 8  # features + level encoding, no noise
    model = make()
    with pytest.raises(ValueError, match="noise input"):
        model(x_dict, h.edge_index_dict, e_dict)
    noise = noise_for(h)
    c = model(x_dict, h.edge_index_dict, e_dict, noise=noise)
    assert torch.equal(c, model(x_dict, h.edge_index_dict, e_dict, noise=noise))
    assert not torch.equal(c, model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h, 1)))


def test_batch_of_two_hierarchies_equals_single_outputs():
    a = toy_hierarchy(nx=6, ny=5, max_levels=3, seed=1)
    b = toy_hierarchy(nx=7, ny=4, max_levels=3, seed=2)
    assert a.num_levels == b.num_levels == 3
    model = make(num_levels=3, num_step_frequencies=3, max_step=5)
    outs = []
    for i, h in enumerate((a, b)):
        x, e = hierarchical_features(h, C)
        outs.append(model(x, h.edge_index_dict, e, noise=noise_for(h, i), step=torch.tensor(i + 1)))
    batch = Batch.from_data_list([a, b])
    x, e = hierarchical_features(batch, C)
    out = model(
        x,
        batch.edge_index_dict,
        e,
        noise=torch.cat([noise_for(a, 0), noise_for(b, 1)]),
        step=torch.tensor([1, 2]),
        batch_dict=batch.batch_dict,
    )
    torch.testing.assert_close(out, torch.cat(outs))


def test_step_conditioning_is_required_when_configured(toy):
    h, x_dict, e_dict = toy
    model = make(num_step_frequencies=4)
    with pytest.raises(ValueError, match="step"):
        model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h))
    a = model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h), step=torch.tensor(0))
    b = model(x_dict, h.edge_index_dict, e_dict, noise=noise_for(h), step=torch.tensor(3))
    assert not torch.allclose(a, b)


def test_padded_contact_tables_with_mask_equal_the_plain_edges(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=4)
    noise = noise_for(h)
    ref = model(x_dict, h.edge_index_dict, e_dict, noise=noise)
    ei_dict, ea_dict, masks = dict(h.edge_index_dict), dict(e_dict), {}
    g = torch.Generator().manual_seed(0)
    for k in range(4):
        key = (f"l{k}", "contact", f"l{k}")
        n, m = h[f"l{k}"].num_nodes, h[key].edge_index.size(1)
        pad = torch.randint(0, n, (2, 7), generator=g)  # junk slots with valid indices
        ei_dict[key] = torch.cat([h[key].edge_index, pad], 1)
        ea_dict[key] = torch.cat([e_dict[key], 1e3 * torch.randn(7, 4, generator=g)])
        masks[key] = torch.arange(m + 7) < m
    out = model(x_dict, ei_dict, ea_dict, noise=noise, contact_mask_dict=masks)
    torch.testing.assert_close(out, ref)


def test_missing_contact_edges_count_as_empty(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=2)
    ei = {k: v for k, v in h.edge_index_dict.items() if k[1] != "contact"}
    empty = {k: (v if k[1] != "contact" else v[:, :0]) for k, v in h.edge_index_dict.items()}
    ea_empty = {k: (v if k[1] != "contact" else v[:0]) for k, v in e_dict.items()}
    a = model(x_dict, ei, e_dict, noise=noise_for(h))
    b = model(x_dict, empty, ea_empty, noise=noise_for(h))
    torch.testing.assert_close(a, b)


def test_bf16_autocast_runs_and_is_close_to_fp32(toy):
    h, x_dict, e_dict = toy
    model = make(num_levels=4, d=32)
    noise = noise_for(h)
    ref = model(x_dict, h.edge_index_dict, e_dict, noise=noise)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(x_dict, h.edge_index_dict, e_dict, noise=noise)
    assert out.dtype == torch.bfloat16 and torch.isfinite(out).all()
    err = (out.float() - ref).norm() / ref.norm()
    assert err < 0.1


def test_aggregation_object_is_copied_into_every_layer(toy):
    from torch_geometric.nn.aggr import MaxAggregation, SoftmaxAggregation

    h, x_dict, e_dict = toy
    torch.manual_seed(0)
    by_name = AMPN(**SIZES, hidden_channels=8, num_levels=3)
    torch.manual_seed(0)
    by_object = AMPN(**SIZES, hidden_channels=8, num_levels=3, aggr=MaxAggregation())
    assert by_object.state_dict().keys() == by_name.state_dict().keys()
    args = (x_dict, h.edge_index_dict, e_dict)
    assert torch.equal(by_name(*args), by_object(*args))
    learnable = AMPN(**SIZES, hidden_channels=8, num_levels=3, aggr=SoftmaxAggregation(learn=True))
    modules = [conv.aggr_module for stack in (learnable.pre, learnable.down, learnable.solve,
                                                learnable.post, learnable.up) for conv in stack]  # fmt: skip
    assert len({id(m) for m in modules}) == learnable.num_layers == 15
    assert count_parameters(learnable) == count_parameters(by_name) + 15  # one temperature per layer
