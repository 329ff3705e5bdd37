"""ROBIN mode: the schedule, K=1 == AMPN with plain MSE, the v-parameterisation, sampling."""

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from torch_ampn.forming import ampn_channels, hierarchical_features
from torch_ampn.nn import DiffusionAMPN, geometric_beta_schedule, pointwise_loss
from torch_ampn.nn import RobinAMPN as AMPN
from torch_ampn.testing import toy_hierarchy

C, G = 3, 2


@pytest.fixture(scope="module")
def toy():
    h = toy_hierarchy(nx=6, ny=5, num_components=C, max_levels=3, num_grippers=G)
    x_dict, e_dict = hierarchical_features(h, C)
    target = torch.randn(h["l0"].num_nodes, 3, generator=torch.Generator().manual_seed(5))
    return h, x_dict, e_dict, target


def make(step_frequencies=0, max_step=20):
    torch.manual_seed(0)
    return AMPN(
        **ampn_channels(C, G),
        hidden_channels=16,
        num_levels=3,
        num_step_frequencies=step_frequencies,
        max_step=max_step,
        noise_channels=3,
    )


def test_geometric_beta_schedule():
    betas = geometric_beta_schedule(5)
    assert betas[0].item() == pytest.approx(1e-4) and betas[-1].item() == pytest.approx(1.0)
    ratios = betas[1:] / betas[:-1]
    ten = torch.full((4,), 10.0, dtype=torch.float64)  # (1e4)^(1/4)
    torch.testing.assert_close(ratios, ten, rtol=1e-12, atol=0)
    assert geometric_beta_schedule(1).tolist() == [1.0]
    for k in (1, 5, 10, 20):
        d = DiffusionAMPN(make(4), num_steps=k)
        assert d.alphas_bar[-1] == 0.0  # zero terminal SNR: x_K is pure noise
        assert torch.all(d.alphas_bar[:-1] > 0)


def test_k1_loss_is_plain_mse_against_the_target(toy):
    h, x_dict, e_dict, target = toy
    model = make()
    diff = DiffusionAMPN(model, num_steps=1)
    eps = torch.randn(target.shape, generator=torch.Generator().manual_seed(1))
    loss = diff.loss(target, x_dict, h.edge_index_dict, e_dict, noise=eps)
    # AMPN: N(0, 1) noise in, residual out, MSE against the target.
    mse = F.mse_loss(model(x_dict, h.edge_index_dict, e_dict, noise=eps), target)
    torch.testing.assert_close(loss, mse)
    # The same with the noise drawn from a generator (noise is drawn first).
    loss_g = diff.loss(target, x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(loss_g, mse)
    # Masked: MSE over the selected nodes only.
    mask = h["l0"].node_type == 0
    loss_m = diff.loss(target, x_dict, h.edge_index_dict, e_dict, noise=eps, node_mask=mask)
    pred = model(x_dict, h.edge_index_dict, e_dict, noise=eps)
    torch.testing.assert_close(loss_m, F.mse_loss(pred[mask], target[mask]))


def test_k1_sampling_is_one_ampn_forward(toy):
    h, x_dict, e_dict, _ = toy
    model = make()
    diff = DiffusionAMPN(model, num_steps=1)
    out = diff.sample(x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(3))
    x_k = torch.randn(out.shape, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(out, model(x_dict, h.edge_index_dict, e_dict, noise=x_k))


def test_v_loss_at_a_fixed_step(toy):
    h, x_dict, e_dict, target = toy
    model = make(4, max_step=4)
    diff = DiffusionAMPN(model, num_steps=5)
    eps = torch.randn(target.shape, generator=torch.Generator().manual_seed(1))
    k = 2
    ab = diff.alphas_bar[k].item()
    x_k = math.sqrt(ab) * target + math.sqrt(1 - ab) * eps
    v = math.sqrt(1 - ab) * target - math.sqrt(ab) * eps
    pred = model(x_dict, h.edge_index_dict, e_dict, noise=x_k, step=torch.tensor([k]))
    loss = diff.loss(target, x_dict, h.edge_index_dict, e_dict, noise=eps, step=torch.tensor([k]))
    torch.testing.assert_close(loss, F.mse_loss(pred, v))
    # x0 is recovered from (x_k, v) at every noise level
    for ab in diff.alphas_bar.tolist():
        xk, vk = diff.q_sample(target, eps, torch.tensor(ab))
        torch.testing.assert_close(math.sqrt(ab) * xk + math.sqrt(1 - ab) * vk, target)


class OracleDenoiser(nn.Module):
    """Predicts the exact v for a data distribution that is a point mass at ``x0``."""

    def __init__(self, x0, alphas_bar):
        super().__init__()
        self.x0, self.alphas_bar = x0, alphas_bar
        self.out_channels = self.noise_channels = x0.size(1)
        self.step_encoding = nn.Identity()  # "has step conditioning"
        self.steps_seen = []

    def forward(self, x_dict, edge_index_dict, edge_attr_dict, noise, step, **kwargs):
        k = int(step)
        self.steps_seen.append(k)
        ab = self.alphas_bar[k].item()
        eps = (noise - math.sqrt(ab) * self.x0) / math.sqrt(1 - ab)
        return math.sqrt(1 - ab) * self.x0 - math.sqrt(ab) * eps


@pytest.mark.parametrize("num_steps", [5, 10, 20])
def test_ancestral_sampling_with_an_oracle_recovers_the_target(num_steps):
    x0 = torch.randn(11, 3, dtype=torch.float64)
    alphas_bar = torch.cumprod(1 - geometric_beta_schedule(num_steps), 0)
    oracle = OracleDenoiser(x0, alphas_bar)
    diff = DiffusionAMPN(oracle, num_steps=num_steps)
    x_dict = {"l0": torch.zeros(11, 1, dtype=torch.float64)}
    out = diff.sample(x_dict, {}, {}, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(out, x0)
    assert oracle.steps_seen == list(range(num_steps - 1, -1, -1))


@pytest.mark.parametrize("num_steps", [1, 5, 10, 20])
def test_sampling_shapes_and_determinism(toy, num_steps):
    h, x_dict, e_dict, target = toy
    diff = DiffusionAMPN(make(4, max_step=num_steps), num_steps=num_steps)
    with torch.no_grad():
        a = diff.sample(x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(0))
        b = diff.sample(x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(0))
        c = diff.sample(x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(1))
    assert a.shape == target.shape and torch.isfinite(a).all()
    assert torch.equal(a, b) and not torch.equal(a, c)
    loss = diff.loss(target, x_dict, h.edge_index_dict, e_dict, generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert loss.ndim == 0 and all(p.grad is not None for p in diff.parameters())


def test_multi_step_needs_step_conditioning():
    with pytest.raises(ValueError, match="step conditioning"):
        DiffusionAMPN(make(0), num_steps=5)
    with pytest.raises(ValueError, match="noise input"):
        DiffusionAMPN(AMPN(10, 4, 8, hidden_channels=8, num_levels=1, noise_channels=0), num_steps=1)


def test_pointwise_loss_by_hand():
    e = torch.tensor([-3.0, -0.5, 0.0, 0.25, 0.5, 2.0], dtype=torch.float64)
    torch.testing.assert_close(pointwise_loss(e), e * e)
    # delta = 0.5: e^2 inside, 2 * 0.5 * |e| - 0.25 outside (continuous at |e| = 0.5)
    want = torch.tensor([2.75, 0.25, 0.0, 0.0625, 0.25, 1.75], dtype=torch.float64)
    torch.testing.assert_close(pointwise_loss(e, 0.5), want)
    # twice torch's Huber loss, with gradient clipped at 2 delta
    torch.testing.assert_close(pointwise_loss(e, 0.5), 2 * F.huber_loss(e, torch.zeros_like(e), "none", 0.5))
    g = e.clone().requires_grad_(True)
    pointwise_loss(g, 0.5).sum().backward()
    torch.testing.assert_close(g.grad, torch.tensor([-1.0, -1.0, 0.0, 0.5, 1.0, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="huber_delta"):
        pointwise_loss(e, 0.0)


def test_k1_huber_loss_by_hand(toy):
    h, x_dict, e_dict, target = toy
    model = make()
    diff = DiffusionAMPN(model, num_steps=1)
    eps = torch.randn(target.shape, generator=torch.Generator().manual_seed(1))
    pred = model(x_dict, h.edge_index_dict, e_dict, noise=eps)
    err = (pred - target).double()
    delta = float(err.abs().median())  # about half the entries on each branch
    by_hand = torch.where(err.abs() <= delta, err * err, 2 * delta * err.abs() - delta * delta)
    mask = h["l0"].node_type == 0
    want, want_m = by_hand.mean(), by_hand[mask].mean()
    args = (target, x_dict, h.edge_index_dict, e_dict)
    loss = diff.loss(*args, noise=eps, huber_delta=delta)
    loss_m = diff.loss(*args, noise=eps, node_mask=mask, huber_delta=delta)
    torch.testing.assert_close(loss.double(), want, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(loss_m.double(), want_m, rtol=1e-5, atol=1e-7)
    assert loss < F.mse_loss(pred, target)  # some errors exceed delta
