"""LayerNormMLP, FourierLevelEncoding and Normalizer."""

import math

import pytest
import torch

import torch_ampn.nn
from torch_ampn.forming import Normalizer
from torch_ampn.nn import FourierLevelEncoding, LayerNormMLP


def test_mlp_is_layernorm_linear_silu_linear():
    torch.manual_seed(0)
    mlp = LayerNormMLP(6, 4, hidden_channels=16)
    assert str(mlp) == "LayerNormMLP(6, 4, hidden_channels=16)"
    x = torch.randn(10, 6)
    z = torch.nn.functional.layer_norm(x, (6,), mlp.norm.weight, mlp.norm.bias, mlp.norm.eps)
    h = z @ mlp.lin1.weight.t() + mlp.lin1.bias
    ref = (h * torch.sigmoid(h)) @ mlp.lin2.weight.t() + mlp.lin2.bias
    torch.testing.assert_close(mlp(x), ref)
    assert mlp.lin1.out_features == 16 and mlp(torch.randn(2, 3, 6)).shape == (2, 3, 4)


def test_fourier_level_encoding_values_and_distinct_codes():
    enc = FourierLevelEncoding(3, max_index=4.0)
    assert enc.out_channels == 6 and str(enc) == "FourierLevelEncoding(3, max_index=4.0)"
    w = [math.pi / 4, math.pi / 8, math.pi / 16]
    expected = [math.sin(2 * x) for x in w] + [math.cos(2 * x) for x in w]
    torch.testing.assert_close(enc(2), torch.tensor(expected))
    codes = enc(torch.arange(5))
    assert codes.shape == (5, 6)
    torch.testing.assert_close(codes[2], enc(2))
    assert torch.cdist(codes, codes).add(torch.eye(5)).min() > 0.1  # all indices told apart
    assert enc(torch.zeros(2, 3)).shape == (2, 3, 6)
    assert "frequencies" not in enc.state_dict()  # a constant, not a parameter or saved state


def test_normalizer_matches_full_data_statistics():
    g = torch.Generator().manual_seed(0)
    data = 1e4 + 0.01 * torch.randn(1000, 3, generator=g, dtype=torch.float64)  # large mean, small std
    data[:, 2] = 5.0  # a constant column
    norm = Normalizer(3)
    torch.testing.assert_close(norm(data.float()), data.float())  # identity before fitting
    for chunk in data.split(137):
        norm.update(chunk)
    torch.testing.assert_close(norm.mean, data.mean(0))
    torch.testing.assert_close(norm.std[:2], data[:, :2].std(0, unbiased=False))
    assert norm.std[2] == 1.0  # eps guard: constant column is only centred
    y = norm(data)
    torch.testing.assert_close(y[:, :2].mean(0), torch.zeros(2, dtype=torch.float64), atol=1e-8, rtol=0)
    torch.testing.assert_close(y[:, :2].std(0, unbiased=False), torch.ones(2, dtype=torch.float64))
    assert torch.all(y[:, 2] == 0)
    torch.testing.assert_close(norm.denormalize(y), data)


def test_normalizer_freeze_and_state_dict():
    norm = Normalizer(2)
    norm.update(torch.tensor([[1.0, 2.0], [3.0, 6.0]]))
    norm.freeze()
    with pytest.raises(RuntimeError, match="frozen"):
        norm.update(torch.ones(1, 2))
    x = torch.randn(4, 2)
    before = norm(x)
    norm(torch.randn(100, 2) * 50)  # using it never changes it
    torch.testing.assert_close(norm(x), before)
    other = Normalizer(2)
    other.load_state_dict(norm.state_dict())
    assert bool(other.frozen)
    torch.testing.assert_close(other(x), before)
    with pytest.raises(ValueError, match="features"):
        Normalizer(3).update(torch.ones(2, 2))


def test_normalizer_without_centering_only_scales():
    g = torch.Generator().manual_seed(1)
    data = 2.0 + 3.0 * torch.randn(500, 2, generator=g, dtype=torch.float64)
    norm = Normalizer(2, center=False)
    norm.update(data)
    std = data.std(0, unbiased=False)
    torch.testing.assert_close(norm.mean, data.mean(0))  # statistics are still kept
    torch.testing.assert_close(norm(data), data / std)
    torch.testing.assert_close(
        norm(torch.zeros(1, 2, dtype=torch.float64)), torch.zeros(1, 2, dtype=torch.float64)
    )
    torch.testing.assert_close(norm.denormalize(norm(data)), data)
    assert "center=False" in repr(norm)


def test_the_generic_core_loads_nothing_of_the_forming_application():
    """``import torch_ampn.nn`` (and the hierarchy, the transforms) in a fresh interpreter."""
    import subprocess
    import sys

    code = (
        "import sys, torch_ampn.nn, torch_ampn.hierarchy, torch_ampn.transforms; "
        "print(' '.join(sorted(sys.modules)))"
    )
    loaded = set(
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        ).stdout.split()
    )
    assert {"torch_ampn.nn.ampn", "torch_ampn.hierarchy.amg", "torch_ampn.transforms.contact"} <= loaded
    application = ("data", "forming", "sim", "rollout", "training", "baselines", "design", "cli", "viz")
    assert not {m for m in loaded if m.split(".")[:2] in [["torch_ampn", a] for a in application]}
    assert not {"meshio", "lightning"} & loaded
    with pytest.raises(AttributeError, match="no attribute 'AMPNSurrogate'"):
        torch_ampn.nn.AMPNSurrogate  # noqa: B018 - the forming names live in torch_ampn.forming
