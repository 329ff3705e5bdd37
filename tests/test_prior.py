"""Priors as model inputs: out-of-fold fits, the prior features, and their path through the windows."""

import dataclasses

import pytest
import torch

from torch_ampn.baselines.prior import fitted_prior, make_prior, out_of_fold_priors
from torch_ampn.data import HierarchyCache, step_sample
from torch_ampn.data.node_type import NodeType
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.forming.features import num_fine_node_features, prior_features
from torch_ampn.testing import small_trajectory

TEMPLATE = small_trajectory(steps=3)
PLY = TEMPLATE.node_type == NodeType.PLY


def _lifted(height: float, force: float):
    """The template with its plies lifted by ``height * t`` mm along e3 at step ``t``."""
    pos = TEMPLATE.pos.clone()
    for t in range(pos.size(0)):
        pos[t, PLY] = TEMPLATE.pos[0, PLY] + torch.tensor([0.0, 0.0, height * t])
    return dataclasses.replace(
        TEMPLATE, pos=pos, gripper_force=torch.tensor([force]), meta={"gripper_edge_fraction": [0.5]}
    )


def test_out_of_fold_mean_prior_is_the_mean_of_the_other_folds():
    heights = [1.0, 2.0, 4.0, 8.0]
    trajs = [_lifted(h, 10.0 * (i + 1)) for i, h in enumerate(heights)]
    priors = out_of_fold_priors("mean_trajectory", trajs, folds=4)  # leave one out
    for i, prior in enumerate(priors):
        others = sum(h for j, h in enumerate(heights) if j != i) / 3  # the hand-computed mean height
        t = 3
        lift = prior[t, PLY] - TEMPLATE.pos[0, PLY]
        torch.testing.assert_close(lift[:, 2], torch.full((int(PLY.sum()),), others * t))
        torch.testing.assert_close(prior[:, ~PLY], trajs[i].pos[:, ~PLY])  # tools: their own motion


def test_out_of_fold_priors_never_see_their_own_trajectory():
    trajs = [_lifted(h, 10.0 * (i + 1)) for i, h in enumerate([1.0, 2.0, 4.0, 8.0, 16.0, 32.0])]
    full = fitted_prior("nearest_setting", trajs)
    # fitted on all, the nearest setting of a training trajectory is itself; out of fold it cannot be
    priors = out_of_fold_priors("nearest_setting", trajs, folds=3, seed=1)
    for traj, prior in zip(trajs, priors, strict=True):
        torch.testing.assert_close(full.predict(traj), traj.pos)
        assert not torch.allclose(prior, traj.pos)


def test_bad_prior_arguments_are_refused():
    with pytest.raises(ValueError, match="prior must be one of"):
        make_prior("kriging")
    with pytest.raises(ValueError, match="folds must be in 2..2"):
        out_of_fold_priors("mean_trajectory", [_lifted(1.0, 1.0), _lifted(2.0, 2.0)], folds=3)


def test_prior_features_are_offset_and_step():
    pos = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    prior_pos = torch.tensor([[0.5, 0.0, 0.0], [1.0, 2.0, 2.0]])
    prior_next = torch.tensor([[0.5, 1.0, 0.0], [2.0, 2.0, 2.0]])
    expected = torch.tensor([[0.5, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, -1.0, 1.0, 0.0, 0.0]])
    torch.testing.assert_close(prior_features(pos, prior_pos, prior_next), expected)


def test_windows_carry_the_prior_and_the_model_reads_it():
    traj = _lifted(1.0, 10.0)
    traj.prior = traj.pos + 0.25  # a prior 0.25 mm off on every axis
    h = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(traj)
    data = step_sample(traj, 2, h)
    torch.testing.assert_close(data["l0"].prior_pos, traj.prior[1])
    torch.testing.assert_close(data["l0"].prior_next, traj.prior[2])
    torch.testing.assert_close(data["l0"].prior_before, traj.prior[0])
    common = dict(num_components=traj.num_components, num_grippers=1, num_levels=2, hidden_channels=8)
    plain, with_prior = AMPNSurrogate(**common), AMPNSurrogate(**common, prior_features=True)
    x_plain = plain._raw_features(data)[0]["l0"]
    x_prior = with_prior._raw_features(data)[0]["l0"]
    assert (
        x_prior.size(1) == x_plain.size(1) + 6 == num_fine_node_features(traj.num_components, 1, prior=True)
    )
    torch.testing.assert_close(x_prior[:, :-6], x_plain)
    torch.testing.assert_close(x_prior[:, -6:-3], torch.full_like(x_prior[:, :3], 0.25))  # the offset
    torch.testing.assert_close(x_prior[:, -3:], traj.pos[2] - traj.pos[1])  # the prior's step
    with pytest.raises(ValueError, match="has no prior"):
        with_prior._raw_features(step_sample(dataclasses.replace(traj, prior=None), 2, h))


def test_a_prior_base_model_learns_the_departure_from_the_priors_step_and_adds_the_step_back():
    """With the truth as prior, the departure is 0: a network that outputs its normalised zero rolls the
    truth out exactly; the same output without prior_base gives the mean training step instead."""
    from torch_ampn.rollout import rollout

    traj = _lifted(1.0, 10.0)
    traj.pos[2:, PLY] += torch.tensor([0.0, 0.5, 0.0])  # steps of two sizes: the mean step is not the truth
    traj.prior = traj.pos.clone()
    h = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(traj)
    common = dict(num_components=traj.num_components, num_grippers=1, num_levels=2, hidden_channels=8,
                  prior_features=True)  # fmt: skip
    based, plain = AMPNSurrogate(**common, prior_base=True), AMPNSurrogate(**common)
    windows = [step_sample(traj, t, h) for t in range(1, traj.num_steps + 1)]
    for s in (based, plain):
        for w in windows:
            s.accumulate_statistics(w)
        s.freeze_statistics()
        s.diffusion.sample = lambda x_dict, *a, **k: torch.zeros(x_dict["l0"].size(0), 3)  # normalised 0
    torch.testing.assert_close(based.target_norm.mean.float(), torch.zeros(3))  # the departure's mean: none
    torch.testing.assert_close(rollout(based.predict_residual, traj, h), traj.pos, atol=1e-5, rtol=0)
    steps = torch.stack([w["l0"].target[PLY] for w in windows])  # [T, n, 3] true steps of the plies
    torch.testing.assert_close(plain.target_norm.mean.float(), steps.reshape(-1, 3).mean(0))
    off = rollout(plain.predict_residual, traj, h)
    assert (off - traj.pos).abs().max() > 0.1  # the mean step, not the truth
    with pytest.raises(ValueError, match="prior_base needs prior_features"):
        AMPNSurrogate(num_levels=2, hidden_channels=8, prior_base=True)
