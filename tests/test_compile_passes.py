"""UnfuseBiasAdd: addmm with fusible users becomes mm + add, with the same result."""

import torch
from torch.fx.experimental.proxy_tensor import make_fx

from torch_ampn.utils.compile_passes import UnfuseBiasAdd

aten = torch.ops.aten


def _targets(gm: torch.fx.GraphModule) -> list:
    return [n.target for n in gm.graph.nodes if n.op == "call_function"]


def test_bias_goes_into_the_following_pointwise_op_but_not_into_a_matmul():
    torch.manual_seed(0)
    w1, b1 = torch.randn(8, 5, dtype=torch.float64), torch.randn(8, dtype=torch.float64)
    w2, b2 = torch.randn(4, 8, dtype=torch.float64), torch.randn(4, dtype=torch.float64)

    def f(x, e):
        h = torch.nn.functional.linear(x, w1, b1)  # used by a matrix product: stays addmm
        z = torch.addmm(e, h, w2.t())  # an added [E, 4] tensor, then relu: unfused
        return torch.relu(z), torch.nn.functional.linear(h, w2, b2).sum(0)

    x, e = torch.randn(6, 5, dtype=torch.float64), torch.randn(6, 4, dtype=torch.float64)
    gm = make_fx(f)(x, e)
    assert _targets(gm).count(aten.addmm.default) == 3
    expected = f(x, e)
    UnfuseBiasAdd()(gm.graph)
    gm.recompile()
    targets = _targets(gm)
    assert targets.count(aten.addmm.default) == 1  # h = linear(x): its user is a matrix product
    assert targets.count(aten.mm.default) == 2 and aten.add.Tensor in targets
    for got, want in zip(gm(x, e), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_a_chain_of_addmm_is_unfused_from_its_end():
    # a linear map of a concatenation, as Inductor splits it: addmm(addmm(b, x, Wx), y, Wy)
    torch.manual_seed(1)
    wx, wy, b = torch.randn(5, 4, dtype=torch.float64), torch.randn(3, 4, dtype=torch.float64), torch.randn(4)
    b = b.double()

    def f(x, y):
        return torch.tanh(torch.addmm(torch.addmm(b, x, wx), y, wy))

    x, y = torch.randn(7, 5, dtype=torch.float64), torch.randn(7, 3, dtype=torch.float64)
    gm = make_fx(f)(x, y)
    assert _targets(gm).count(aten.addmm.default) == 2
    UnfuseBiasAdd()(gm.graph)
    gm.recompile()
    targets = _targets(gm)
    assert aten.addmm.default not in targets  # the inner one too, once its user is an add
    assert targets.count(aten.mm.default) == 2 and targets.count(aten.add.Tensor) == 2
    want = torch.tanh(b + x @ wx + y @ wy)
    torch.testing.assert_close(gm(x, y), want, rtol=1e-12, atol=1e-12)


def test_scaled_addmm_is_left_alone():
    a, b, c = torch.randn(3, 2), torch.randn(2, 4), torch.randn(3, 4)
    gm = make_fx(lambda a, b, c: torch.relu(torch.addmm(c, a, b, beta=0.5)))(a, b, c)
    UnfuseBiasAdd()(gm.graph)
    assert aten.addmm.default in _targets(gm)


def test_compiled_with_the_pass_equals_eager():
    torch.manual_seed(0)
    nn = torch.nn
    net = nn.Sequential(nn.Linear(5, 16), nn.LayerNorm(16), nn.SiLU(), nn.Linear(16, 3))
    x = torch.randn(40, 5)
    compiled = torch.compile(net, options={"post_grad_custom_post_pass": UnfuseBiasAdd()})
    with torch.no_grad():
        torch.testing.assert_close(compiled(x), net(x), rtol=1e-5, atol=1e-6)
