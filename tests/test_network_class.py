"""AMPNSurrogate(network_class=...): another network in place of the AMPN, built, fed and rolled out."""

import pytest
import torch

from torch_ampn.data import HierarchyCache, step_sample
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.forming.features import hierarchical_features
from torch_ampn.forming.surrogate import import_network_class
from torch_ampn.rollout import rollout
from torch_ampn.rollout.fast import fast_path_supported


@pytest.fixture(scope="module")
def window(small_runs):
    traj = small_runs[0]
    hierarchy = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(traj)
    return traj, hierarchy


def _fitted(network_class: str, window, **options) -> tuple[AMPNSurrogate, object]:
    traj, hierarchy = window
    surrogate = AMPNSurrogate(num_levels=1, network_class=network_class, network_options=options)
    data = surrogate.contact(step_sample(traj, 3, hierarchy))
    surrogate.accumulate_statistics(data)
    surrogate.freeze_statistics()
    return surrogate, data


def test_the_network_is_built_with_the_surrogates_sizes_and_its_options(window):
    surrogate, _ = _fitted("helpers:PointwiseNetwork", window, scale=0.5)
    net = surrogate.model
    assert type(net).__name__ == "PointwiseNetwork" and net.scale == 0.5
    fine_in = surrogate.node_norm["fine"].mean.numel()
    assert net.linear.in_features == fine_in + 3  # the features plus the noise input
    assert fast_path_supported(surrogate) == "network_class 'helpers:PointwiseNetwork' is not an AMPN"
    assert "network_class='helpers:PointwiseNetwork'" in repr(surrogate)


def test_predict_residual_is_the_networks_output_on_the_normalised_features(window):
    surrogate, data = _fitted("helpers:PointwiseNetwork", window)
    x_raw = hierarchical_features(data, surrogate.num_components, 1, alpha=surrogate.gripper_alpha)[0]["l0"]
    fine_norm = surrogate.node_norm["fine"]
    x = ((x_raw.double() - fine_norm.mean) / fine_norm.std).float()  # by hand, float64 statistics
    noise = torch.randn(x.size(0), 3, generator=torch.Generator().manual_seed(5))
    expected = surrogate.model.linear(torch.cat([x, noise], dim=-1)).double()
    target = surrogate.target_norm
    expected = expected * target.std + target.mean  # the target's own scale, mm
    got = surrogate.predict_residual(data, torch.Generator().manual_seed(5))
    torch.testing.assert_close(got.double(), expected, atol=1e-5, rtol=1e-5)
    assert set(surrogate.model.last_x_dict) == {"l0"}  # no positions unless asked for


def test_a_network_that_needs_positions_gets_them_normalised(window):
    surrogate, data = _fitted("helpers:PositionsNetwork", window)
    surrogate.predict_residual(data, torch.Generator().manual_seed(0))
    seen = surrogate.model.last_x_dict
    norm = surrogate.position_norm
    fine = data["l0"]
    for key, pos in (("pos", fine.pos), ("pos0", fine.pos0)):
        torch.testing.assert_close(
            seen[key].double(), (pos.double() - norm.mean) / norm.std, atol=1e-5, rtol=0
        )


def test_loss_trains_the_network_and_the_rollout_takes_the_plain_path(window):
    traj, hierarchy = window
    surrogate, data = _fitted("helpers:PointwiseNetwork", window)
    loss = surrogate.loss(data, generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert surrogate.model.linear.weight.grad.abs().sum() > 0
    with pytest.warns(RuntimeWarning, match="no fast rollout.*is not an AMPN"):
        fast = rollout(surrogate, traj, hierarchy, fast=True, generator=torch.Generator().manual_seed(1))
    plain = rollout(
        lambda d: surrogate.predict_residual(d, torch.Generator().manual_seed(1)),
        traj,
        hierarchy,
        surrogate.contact,
    )
    assert fast.shape == traj.pos.shape and torch.isfinite(fast).all()
    assert torch.equal(fast[0], plain[0]) and torch.equal(
        fast[:, ~traj.ply_mask], traj.pos[:, ~traj.ply_mask]
    )


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("PointwiseNetwork", "is not 'package.module:name'"),
        ("no_such_module:Net", "cannot import 'no_such_module'"),
        ("helpers:NoSuchNetwork", "'helpers' has no 'NoSuchNetwork'"),
        ("helpers:tiny_cli_config", "'helpers:tiny_cli_config' is not a torch.nn.Module class"),
    ],
)
def test_a_bad_network_class_is_refused_in_one_line(path, message):
    with pytest.raises(ValueError, match=message) as err:
        import_network_class(path)
    assert "\n" not in str(err.value) and str(err.value).startswith("network_class: ")


def test_dotted_form_names_the_same_class():
    assert import_network_class("helpers.PointwiseNetwork") is import_network_class(
        "helpers:PointwiseNetwork"
    )
