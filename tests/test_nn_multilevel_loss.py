"""The multilevel loss: restriction by hand and against a dense float64 reference."""

from __future__ import annotations

import pytest
import torch

from torch_ampn.nn import multilevel_mse, restrict_mean


def _dense_reference(error, mask, prolongators, lam):
    """The module docstring's formula with dense |P| matrices, in float64."""
    e, w = error.double(), mask.double()
    c = e.size(1)
    loss = (e.square() * w[:, None]).sum() / (w.sum() * c)
    for p in prolongators:
        a = p.double().abs() * w[:, None]  # [N_f, N_c]: |P_iJ| W_i
        w = a.sum(0)  # [N_c]
        e = (a.t() @ e) / w.clamp(min=1e-300)[:, None]  # [N_c, C]
        loss = loss + lam * (e.square() * w[:, None]).sum() / (w.sum() * c)
    return loss


def _edges(p):
    """Down edges (fine i, coarse J) and values of a dense prolongator ``[N_f, N_c]``."""
    fine, coarse = p.nonzero(as_tuple=True)
    return torch.stack([fine, coarse]), p[fine, coarse], p.size(1)


def test_restrict_mean_by_hand():
    # fine nodes 0, 1 -> coarse 0 (weights 1, 3); fine 2, 3 -> coarse 1; node 3 masked out
    index = torch.tensor([[0, 1, 2, 3], [0, 0, 1, 1]])
    weight = torch.tensor([1.0, -3.0, 2.0, 1.0])  # the magnitude counts
    values = torch.tensor([[4.0, 0.0], [0.0, 8.0], [5.0, 5.0], [100.0, 100.0]])
    mask = torch.tensor([1.0, 1.0, 1.0, 0.0])
    mean, total = restrict_mean(values, mask, index, weight, 3)
    torch.testing.assert_close(mean, torch.tensor([[1.0, 6.0], [5.0, 5.0], [0.0, 0.0]]))
    torch.testing.assert_close(total, torch.tensor([4.0, 2.0, 0.0]))  # coarse 2 has no fine node


def test_multilevel_mse_matches_dense_reference():
    g = torch.Generator().manual_seed(0)
    p1 = torch.rand(12, 5, generator=g) * (torch.rand(12, 5, generator=g) < 0.4)
    p1[torch.arange(12), torch.arange(12) % 5] = 1.0  # every fine node has a coarse parent
    p2 = torch.rand(5, 2, generator=g) - 0.3  # mixed signs
    p2[torch.arange(5), torch.arange(5) % 2] = 1.0
    error = torch.randn(12, 3, generator=g)
    mask = torch.rand(12, generator=g) < 0.7
    down = [_edges(p1), _edges(p2)]
    for lam in (0.0, 0.5, 2.0):
        got = multilevel_mse(error, mask, down, lam)
        want = _dense_reference(error, mask, [p1, p2], lam)
        torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-7)
    # lam = 0 is the masked MSE; no mask = every node
    torch.testing.assert_close(multilevel_mse(error, mask, down, 0.0), error[mask].square().mean())
    torch.testing.assert_close(multilevel_mse(error, None, down, 0.0), error.square().mean())


def test_smooth_error_counts_on_every_level_jitter_only_on_the_fine_one():
    # aggregates of two nodes with equal weights
    index = torch.stack([torch.arange(8), torch.arange(8) // 2])
    down = [(index, torch.ones(8), 4)]
    smooth = torch.full((8, 3), 0.5)
    jitter = torch.tensor([1.0, -1.0]).repeat(4)[:, None].expand(8, 3).contiguous() * 0.5
    # a constant error: its restriction is the same constant, so the loss is (1 + lam) e^2
    torch.testing.assert_close(multilevel_mse(smooth, None, down, 2.0), torch.tensor(3 * 0.25))
    # +-e within each aggregate cancels: the coarse term is zero, only the fine MSE stays
    torch.testing.assert_close(multilevel_mse(jitter, None, down, 2.0), torch.tensor(0.25))


def test_gradient_of_coarse_term_is_the_restricted_error():
    index = torch.stack([torch.arange(4), torch.tensor([0, 0, 1, 1])])
    error = torch.tensor([[1.0], [3.0], [2.0], [-2.0]], requires_grad=True)
    loss = multilevel_mse(error, None, [(index, torch.ones(4), 2)], 1.0)
    loss.backward()
    # fine term sum(e^2) / 4: gradient 2 e_i / 4. Coarse term (W_0 m_0^2 + W_1 m_1^2) / (W_0 + W_1)
    # with W = (2, 2), m = (2, 0): gradient 2 W_J m_J / 4 * dm_J/de_i = m_J * (1/2) * 2 = (1, 1, 0, 0)
    fine = 2 * error.detach() / 4
    coarse = torch.tensor([[1.0], [1.0], [0.0], [0.0]])
    torch.testing.assert_close(error.grad, fine + coarse)


def test_surrogate_rejects_bad_coarse_loss_weight():
    from torch_ampn.forming import AMPNSurrogate

    with pytest.raises(ValueError, match="coarse_loss_weight"):
        AMPNSurrogate(coarse_loss_weight=-1.0)
    with pytest.raises(ValueError, match="huber_delta"):
        AMPNSurrogate(coarse_loss_weight=1.0, huber_delta=0.1)
