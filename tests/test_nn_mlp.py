"""LayerNormMLP.forward_edges against the plain LayerNormMLP applied to the gathered, concatenated input."""

import pytest
import torch

from torch_ampn.nn import LayerNormMLP


def _reference(mlp: LayerNormMLP, x_dst, x_src, edge_attr, edge_index):
    src, dst = edge_index
    return mlp(torch.cat([x_dst[dst], x_src[src], edge_attr], dim=-1))


def _randomised_mlp(in_channels: int, out_channels: int, hidden: int) -> LayerNormMLP:
    mlp = LayerNormMLP(in_channels, out_channels, hidden_channels=hidden).double()
    with torch.no_grad():  # non-trivial affine layer norm, so gamma and beta are exercised
        mlp.norm.weight.uniform_(0.5, 1.5)
        mlp.norm.bias.normal_()
    return mlp


@pytest.mark.parametrize(
    ("same_nodes", "sizes"),
    [(True, (4, 4, 4)), (True, (8, 8, 1)), (False, (4, 4, 4)), (False, (3, 5, 2)), (False, (8, 8, 1))],
)
def test_forward_edges_matches_concatenated_mlp_float64(same_nodes, sizes):
    torch.manual_seed(0)
    f_dst, f_src, f_edge = sizes
    mlp = _randomised_mlp(sum(sizes), 3, 16)
    x_dst = torch.randn(11, f_dst, dtype=torch.float64, requires_grad=True)
    x_src = x_dst if same_nodes else torch.randn(7, f_src, dtype=torch.float64, requires_grad=True)
    edge_index = torch.stack([torch.randint(0, x_src.size(0), (40,)), torch.randint(0, 11, (40,))])
    edge_attr = torch.randn(40, f_edge, dtype=torch.float64, requires_grad=True)

    out = mlp.forward_edges(x_dst, x_src, edge_attr, edge_index)
    ref = _reference(mlp, x_dst, x_src, edge_attr, edge_index)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)

    # Same gradients for the inputs and every parameter.
    grad_out = torch.randn_like(out)
    inputs = [x_dst, edge_attr, *mlp.parameters()] + ([] if same_nodes else [x_src])
    grads = torch.autograd.grad(out, inputs, grad_out)
    grads_ref = torch.autograd.grad(ref, inputs, grad_out)
    for g, g_ref in zip(grads, grads_ref, strict=True):
        torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-10)


def test_forward_edges_with_residual_adds_the_linear_map_of_the_edge_features():
    torch.manual_seed(1)
    mlp = _randomised_mlp(4 + 4 + 5, 3, 16)
    x = torch.randn(9, 4, dtype=torch.float64)
    edge_index = torch.stack([torch.randint(0, 9, (30,)), torch.randint(0, 9, (30,))])
    edge_attr = torch.randn(30, 5, dtype=torch.float64, requires_grad=True)
    w = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)

    out = mlp.forward_edges(x, x, edge_attr, edge_index, residual=w)
    ref = edge_attr @ w.t() + _reference(mlp, x, x, edge_attr, edge_index)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    grad_out = torch.randn_like(out)
    for g, g_ref in zip(
        torch.autograd.grad(out, [edge_attr, w], grad_out),
        torch.autograd.grad(ref, [edge_attr, w], grad_out),
        strict=True,
    ):
        torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-10)


def test_forward_edges_float32_stable_for_large_mean_features():
    """Features with a mean far above their spread: no E[x^2] - E[x]^2 cancellation."""
    torch.manual_seed(1)
    mlp = _randomised_mlp(12, 4, 8)
    x = 1e3 + torch.randn(20, 4, dtype=torch.float64)
    e = 1e3 + torch.randn(50, 4, dtype=torch.float64)
    edge_index = torch.randint(0, 20, (2, 50))
    ref = _reference(mlp, x, x, e, edge_index)  # float64 reference
    out32 = mlp.float().forward_edges(x.float(), x.float(), e.float(), edge_index)
    plain32 = _reference(mlp, x.float(), x.float(), e.float(), edge_index)
    err = (out32.double() - ref).abs().max().item()
    err_plain = (plain32.double() - ref).abs().max().item()
    assert err < 1e-2 and err <= 10 * err_plain + 1e-4


def test_forward_edges_rejects_sizes_that_do_not_add_up():
    mlp = LayerNormMLP(9, 2, hidden_channels=4)
    x = torch.randn(5, 3)
    with pytest.raises(ValueError, match=r"3 \+ 3 \+ 2 do not add up to in_channels=9"):
        mlp.forward_edges(x, x, torch.randn(6, 2), torch.zeros(2, 6, dtype=torch.long))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_edges_without_autograd_is_bitwise_the_autograd_path_and_leaves_its_inputs(dtype):
    torch.manual_seed(2)
    mlp = _randomised_mlp(4 + 4 + 5, 3, 16).to(dtype)
    x = torch.randn(9, 4, dtype=dtype)
    edge_index = torch.stack([torch.randint(0, 9, (30,)), torch.randint(0, 9, (30,))])
    edge_attr = torch.randn(30, 5, dtype=dtype)
    w = torch.randn(3, 5, dtype=dtype)
    x_copy, e_copy = x.clone(), edge_attr.clone()
    for residual in (None, w):
        with_grad = mlp.forward_edges(x, x, edge_attr, edge_index, residual=residual)
        assert with_grad.requires_grad
        with torch.no_grad():  # the in-place path
            without = mlp.forward_edges(x, x, edge_attr, edge_index, residual=residual)
        assert torch.equal(without, with_grad.detach())
    assert torch.equal(x, x_copy) and torch.equal(edge_attr, e_copy)
