"""Rollouts, the RMSE metric, the trivial baselines and process settings without ground truth."""

import math

import pytest
import torch

from torch_ampn.baselines import RigidWithPunch, static_plies
from torch_ampn.data import HierarchyCache, NodeType, step_sample
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.rollout import one_step_predictions, rollout, rollout_plain, rollout_rmse
from torch_ampn.sim import process_trajectories, process_trajectory


@pytest.fixture(scope="module")
def hierarchy(small_runs):
    return HierarchyCache(None, max_levels=3, min_coarse_nodes=4)(small_runs[0])


def test_rmse_matches_hand_computation():
    true = torch.zeros(3, 2, 3)
    pred = true.clone()
    pred[1, 0] = torch.tensor([3.0, 0.0, 0.0])  # step 1: one node off by 3 along e1
    pred[2, 1] = torch.tensor([1.0, 2.0, 2.0])  # step 2: the other node off by (1, 2, 2)
    rmse = rollout_rmse(pred, true)
    assert rmse[0] == 0
    assert rmse[1] == pytest.approx(math.sqrt(9.0 / 6.0))
    assert rmse[2] == pytest.approx(math.sqrt(9.0 / 6.0))
    # with a mask only the selected node counts
    masked = rollout_rmse(pred, true, torch.tensor([True, False]))
    assert masked[1] == pytest.approx(math.sqrt(9.0 / 3.0)) and masked[2] == 0


def test_oracle_rollout_reproduces_the_trajectory_and_its_windows(small_runs, hierarchy):
    traj = small_runs[0]
    seen = []

    def oracle(data):
        t = int(data.step)
        expected = step_sample(traj, t, hierarchy)
        seen.append(t)
        # with exact predictions every input of a rollout window equals the ground-truth window
        for name in ("pos", "prev_disp", "bc_disp"):
            torch.testing.assert_close(data["l0"][name], expected["l0"][name], atol=1e-4, rtol=0)
        torch.testing.assert_close(data.gripper_pos, expected.gripper_pos, atol=1e-4, rtol=0)
        return traj.pos[t] - data["l0"].pos

    pred = rollout(oracle, traj, hierarchy)
    assert seen == list(range(1, traj.num_steps + 1))
    torch.testing.assert_close(pred, traj.pos, atol=1e-4, rtol=0)


def test_a_constant_error_per_step_compounds_in_the_rollout_and_not_in_one_step(small_runs, hierarchy):
    """A predictor off by a constant ``b`` per step (hand computation): the teacher-forced step errs
    |b| at every step; the rollout accumulates it, t |b| at step t; from the true state at step s,
    (t - s) |b|, and rows 0..s are the trajectory's own."""
    traj = small_runs[0]
    bias = torch.tensor([0.3, -0.4, 1.2])  # |b| = 1.3 mm; the RMSE over 3 coordinates is |b| / sqrt 3

    def biased(data):
        t = int(data.step)
        return traj.pos[t] - traj.pos[t - 1] + bias  # the true step's residual, plus b, whatever the state

    ply = traj.ply_mask
    per_step = 1.3 / math.sqrt(3)
    steps = torch.arange(traj.num_steps + 1, dtype=torch.float64)
    one = rollout_rmse(one_step_predictions(biased, traj, hierarchy), traj.pos, ply).double()
    torch.testing.assert_close(one[1:], torch.full_like(one[1:], per_step), atol=1e-4, rtol=0)
    full = rollout_rmse(rollout_plain(biased, traj, hierarchy), traj.pos, ply).double()
    torch.testing.assert_close(full, steps * per_step, atol=1e-3, rtol=0)
    start = 3
    late = rollout_plain(biased, traj, hierarchy, start=start)
    assert torch.equal(late[: start + 1], traj.pos[: start + 1].float())
    expected = (steps - start).clamp_min(0) * per_step
    torch.testing.assert_close(rollout_rmse(late, traj.pos, ply).double(), expected, atol=1e-3, rtol=0)
    tools = ~ply
    assert torch.equal(late[:, tools], traj.pos[:, tools].float())  # tools on their path
    with pytest.raises(ValueError, match="start must be in 0..5"):
        rollout_plain(biased, traj, hierarchy, start=traj.num_steps)


def test_rollout_keeps_tools_on_their_prescribed_path(small_runs, hierarchy):
    traj = small_runs[0]
    surrogate = AMPNSurrogate(
        hidden_channels=8,
        num_levels=hierarchy.num_levels,
        pre_layers=1,
        down_layers=1,
        solve_layers=1,
        post_layers=1,
        up_layers=1,
    )
    generator = torch.Generator().manual_seed(0)
    pred = rollout(lambda d: surrogate.predict_residual(d, generator), traj, hierarchy, surrogate.contact)
    tools = traj.node_type != NodeType.PLY
    assert torch.equal(pred[:, tools], traj.pos[:, tools])  # exactly, not approximately
    assert (pred[-1, ~tools] - traj.pos[0, ~tools]).abs().max() > 0  # the untrained model does move plies
    assert torch.isfinite(pred).all()


def test_rollout_never_reads_future_ply_positions(small_runs, hierarchy):
    traj = small_runs[0]
    poisoned = traj.to("cpu")
    poisoned.pos = traj.pos.clone()
    poisoned.pos[1:, traj.ply_mask] = float("nan")  # a rollout must not need them

    def predictor(data):
        assert torch.isfinite(data["l0"].pos).all()
        return torch.zeros_like(data["l0"].pos)

    pred = rollout(predictor, poisoned, hierarchy)
    assert torch.isfinite(pred).all()


def test_static_baseline_error_is_the_rms_displacement(small_runs, hierarchy):
    traj = small_runs[0]
    pred = rollout(static_plies, traj, hierarchy)
    ply = traj.ply_mask
    u = traj.pos[:, ply] - traj.pos[0, ply]  # [T+1, n, 3]
    expected = u.double().square().mean(dim=(1, 2)).sqrt()
    torch.testing.assert_close(rollout_rmse(pred, traj.pos, ply).double(), expected, atol=1e-5, rtol=1e-5)


def test_rigid_with_punch_by_hand():
    data = HierarchicalData()
    fine = data["l0"]
    fine.pos = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [5.0, 0.0, 0.0], [0.0, 1.5, 0.0], [9.0, 0, 0]]
    )
    fine.node_type = torch.tensor([NodeType.PUNCH, NodeType.PLY, NodeType.PLY, NodeType.PUNCH, NodeType.DIE])
    fine.bc_disp = torch.tensor([[0.0, 0.0, -1.0], [0, 0, 0], [0, 0, 0], [0.0, 0.0, -2.0], [0, 0, 0]])
    out = RigidWithPunch(touch_radius=2.0)(data)
    expected = torch.zeros(5, 3)
    expected[1] = torch.tensor([0.0, 0.0, -1.0])  # nearest punch node 0 (distance 1 < 1.80 to node 3)
    # node 2 is 5 mm from the punch: stays; tools get zero (their motion is prescribed anyway)
    assert torch.equal(out, expected)
    with pytest.raises(ValueError, match="touch_radius"):
        RigidWithPunch(0.0)


def test_process_trajectory_matches_the_simulated_setting(small_runs, small_sim):
    traj = small_runs[1]
    setting = process_trajectory(small_sim, seed=4)
    assert torch.equal(setting.gripper_nodes, traj.gripper_nodes)
    torch.testing.assert_close(setting.gripper_anchor, traj.gripper_anchor)
    torch.testing.assert_close(setting.gripper_force, traj.gripper_force)
    tools = traj.node_type != NodeType.PLY
    torch.testing.assert_close(setting.pos[:, tools], traj.pos[:, tools])
    assert torch.equal(setting.pos[:, ~tools], traj.pos[:1, ~tools].expand(small_sim.num_steps + 1, -1, -1))
    assert setting.meta["ground_truth"] is False
    explicit = process_trajectory(
        small_sim, traj.meta["gripper_edge_fraction"], traj.gripper_force.double().tolist()
    )
    assert torch.equal(explicit.gripper_nodes, traj.gripper_nodes)
    # many settings at once, the mesh and tool motion built once: each as built alone
    settings = [
        (traj.meta["gripper_edge_fraction"], traj.gripper_force.double().tolist()),
        ([0.2, 0.9], [5.0, 70.0]),
    ]
    first, second = process_trajectories(small_sim, settings)
    for many, (where, force) in zip((first, second), settings, strict=True):
        one = process_trajectory(small_sim, where, force)
        for name in ("pos", "time", "fiber", "component", "node_type", "gripper_nodes", "gripper_anchor"):
            assert torch.equal(getattr(many, name), getattr(one, name)), name
        assert torch.equal(many.gripper_force, one.gripper_force) and many.meta == one.meta
    first.pos[1:] += 1.0  # writing into one (as a prediction buffer) leaves the other alone
    assert torch.equal(second.pos, process_trajectory(small_sim, *settings[1]).pos)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(gripper_positions=[0.5], gripper_forces=[10.0, 10.0]), "gripper_positions needs 2"),
        (dict(gripper_positions=[0.5, 1.5], gripper_forces=[10.0, 10.0]), r"in \[0, 1\]"),
        (dict(gripper_positions=[0.5, 0.5], gripper_forces=[-1.0, 10.0]), ">= 0 N"),
        (dict(gripper_positions=[0.5, float("nan")], gripper_forces=[1.0, 1.0]), "finite"),
        (dict(gripper_positions=[0.5, 0.5]), "needs gripper_positions and gripper_forces"),
        (dict(seed=1, gripper_positions=[0.5, 0.5]), "either a seed"),
    ],
)
def test_process_trajectory_refuses_bad_settings(small_sim, kwargs, match):
    with pytest.raises(ValueError, match=match):
        process_trajectory(small_sim, **kwargs)


def test_contact_edges_from_the_initial_state_serve_every_step(small_runs, hierarchy):
    from torch_ampn.transforms import ComponentRadiusGraph

    traj = small_runs[0]
    initial = ComponentRadiusGraph(12.0, 1, positions="initial")
    expected = ComponentRadiusGraph(12.0, 1)(step_sample(traj, 1, hierarchy))  # built from x^0
    seen = []

    def moving(data):  # a predictor that moves the plies, so that current-position edges would change
        seen.append([data.contact(k).edge_index.clone() for k in range(data.num_levels)])
        return torch.full_like(data["l0"].pos, 0.7)

    rollout(moving, traj, hierarchy, initial)
    assert len(seen) == traj.num_steps
    for edges in seen:
        for k, edge_index in enumerate(edges):
            assert torch.equal(edge_index, expected.contact(k).edge_index)
    current = []
    rollout(lambda d: current.append(d.contact(0).edge_index.clone()) or torch.full_like(d["l0"].pos, 0.7),
            traj, hierarchy, ComponentRadiusGraph(12.0, 1))  # fmt: skip
    assert not all(torch.equal(e, current[0]) for e in current)


def test_a_one_step_trajectory_without_any_contact_edge_rolls_out(small_sim):
    """Cases that must work: no contact edge anywhere (components apart), a single saved step."""
    import dataclasses

    from torch_ampn.sim import simulate

    traj = simulate(dataclasses.replace(small_sim, num_steps=1), seed=3)
    hierarchy = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)(traj)
    sizes = dict(hidden_channels=8, mlp_channels=8, num_levels=2)
    surrogate = AMPNSurrogate(**sizes, contact_radius=1e-6, contact_k=1)
    window = surrogate.contact(step_sample(traj, 1, hierarchy))
    assert all(window.contact(k).edge_index.size(1) == 0 for k in range(2))
    surrogate.accumulate_statistics(window)
    surrogate.freeze_statistics()
    pred = rollout(lambda d: surrogate.predict_residual(d, torch.Generator().manual_seed(0)), traj, hierarchy,
                   surrogate.contact)  # fmt: skip
    assert pred.shape == traj.pos.shape and torch.isfinite(pred).all()
    tools = ~traj.ply_mask
    assert torch.equal(pred[:, tools], traj.pos[:, tools])


def test_a_mesh_with_a_single_component_trains_and_predicts():
    """Cases that must work: one component (a single ply, no tools): no contact edges, finite outputs."""
    from torch_ampn.data import NodeType
    from torch_ampn.testing import toy_hierarchy

    data = toy_hierarchy(nx=6, ny=5, num_components=1, max_levels=2, min_coarse_nodes=4)
    fine = data["l0"]
    fine.node_type = torch.full_like(fine.node_type, int(NodeType.PLY))
    fine.bc_disp = torch.zeros_like(fine.bc_disp)
    fine.ply_mask = torch.ones(fine.num_nodes, dtype=torch.bool)
    fine.target = 0.01 * torch.randn(fine.num_nodes, 3, generator=torch.Generator().manual_seed(1))
    for k in range(data.num_levels):
        data.level(k).node_type = fine.node_type[data.fine_index(k)]
        data.level(k).component = fine.component[data.fine_index(k)]
    sizes = dict(hidden_channels=8, mlp_channels=8, num_levels=2)
    surrogate = AMPNSurrogate(num_components=1, **sizes, contact_radius=0.6)
    data = surrogate.contact(data)
    assert all(data.contact(k).edge_index.size(1) == 0 for k in range(2))
    surrogate.accumulate_statistics(data)
    surrogate.freeze_statistics()
    loss = surrogate.loss(data, generator=torch.Generator().manual_seed(0))
    loss.backward()
    residual = surrogate.predict_residual(data, torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and residual.shape == (fine.num_nodes, 3) and torch.isfinite(residual).all()
