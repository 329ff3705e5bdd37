"""New gripper settings on a template trajectory: the embedded simulator's part as the reference."""

import dataclasses

import pytest
import torch
import yaml

from torch_ampn.data.template import boundary_loop, gripper_edge, template_settings
from torch_ampn.sim import process_trajectory
from torch_ampn.training import AMPNDataModule

SAME = ["pos", "time", "component", "node_type", "fiber", "gripper_nodes", "gripper_anchor", "gripper_force"]


@pytest.mark.parametrize(
    "where, force", [([0.2, 0.7], [10.0, 90.0]), ([0.0, 1.0], [0.0, 100.0]), ([0.5, 0.33], [5.0, 5.0])]
)
def test_edge_fractions_on_a_template_are_the_simulators_settings(small_runs, small_sim, where, force):
    """A simulated run as the template: its mesh and tools with new settings = process_trajectory's."""
    ours = template_settings(small_runs[0], force, gripper_positions=where)
    reference = process_trajectory(small_sim, where, force)
    for f in SAME:
        torch.testing.assert_close(getattr(ours, f), getattr(reference, f), atol=1e-5, rtol=0, msg=f)
    assert ours.meta["ground_truth"] is False and ours.meta["gripper_edge_fraction"] == where


def test_gripper_nodes_give_the_needle_through_the_stack(small_runs, small_sim):
    template = small_runs[0]
    reference = process_trajectory(small_sim, [0.3, 0.6], [20.0, 30.0])
    bases = reference.gripper_nodes[:, 0].tolist()
    ours = template_settings(template, [20.0, 30.0], gripper_nodes=bases)
    assert torch.equal(ours.gripper_nodes, reference.gripper_nodes)  # the nearest node of every ply
    torch.testing.assert_close(ours.gripper_anchor, reference.gripper_anchor)


def test_the_edges_of_the_simulators_grippers(small_runs, small_sim):
    lx, ly = small_sim.ply_size
    (a0, b0), (a1, b1) = (gripper_edge(small_runs[0], g) for g in range(2))
    z = float(small_runs[0].pos[0, 0, 2])
    assert a0.tolist() == pytest.approx([lx, 0, z]) and b0.tolist() == pytest.approx([lx, ly, z])
    assert a1.tolist() == pytest.approx([0, ly, z]) and b1.tolist() == pytest.approx([lx, ly, z])


def test_boundary_loop_of_a_grid_by_hand():
    # 2 x 2 quads on a 3 x 3 grid of nodes 0..8 (row by row): the boundary is the 8 outer nodes
    cells = torch.tensor([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]])
    loop = boundary_loop(cells)
    assert sorted(loop) == [0, 1, 2, 3, 5, 6, 7, 8] and 4 not in loop
    ring = [0, 1, 2, 5, 8, 7, 6, 3]
    k = ring.index(loop[0])
    assert loop in (ring[k:] + ring[:k], (ring[k::-1] + ring[:k:-1]))  # one way round or the other


def test_settings_that_do_not_fit_the_template_are_refused(small_runs):
    t = small_runs[0]
    punch = int(torch.nonzero(t.node_type == 1)[0])
    for kwargs, message in [
        ({"gripper_positions": [0.5, 1.5]}, r"2 edge fractions in \[0, 1\] needed"),
        ({"gripper_positions": [0.5]}, r"2 edge fractions"),
        ({"gripper_nodes": [0, punch]}, rf"gripper_nodes\[1\]: node {punch} is not a node of the first ply"),
        ({}, "give either gripper_positions"),
        ({"gripper_positions": [0.5, 0.5], "gripper_nodes": [0, 1]}, "give either gripper_positions"),
    ]:
        with pytest.raises(ValueError, match=message):
            template_settings(t, [1.0, 2.0], **kwargs)
    with pytest.raises(ValueError, match="2 finite forces >= 0 N needed"):
        template_settings(t, [1.0, -2.0], gripper_positions=[0.5, 0.5])
    bare = dataclasses.replace(
        t,
        gripper_nodes=t.gripper_nodes[:0],
        gripper_anchor=t.gripper_anchor[:0],
        gripper_force=t.gripper_force[:0],
    )
    with pytest.raises(ValueError, match="the template has no grippers"):
        template_settings(bare, [], gripper_positions=[])


def test_predict_with_a_template_equals_predict_on_the_embedded_dataset(tiny_data, tmp_path):
    data_dir = tiny_data
    """The data module's predict split: a test run as the template gives the simulator's settings."""
    settings = tmp_path / "settings.yaml"
    settings.write_text(yaml.safe_dump([
        {"name": "a", "gripper_positions": [0.2, 0.8], "gripper_forces": [90.0, 10.0]},
        {"name": "b", "gripper_nodes": [3, 30], "gripper_forces": [1.0, 2.0]},
    ]))  # fmt: skip
    template = sorted((data_dir / "test").glob("*.pt"))[0]
    dm = AMPNDataModule(
        str(data_dir),
        generate=False,
        predict_file=str(settings),
        predict_template=str(template),
        min_coarse_nodes=4,
    )
    dm.setup("predict")
    a, b = (item.trajectory for item in dm._splits["predict"])
    reference = process_trajectory(dm.simulator_config(), [0.2, 0.8], [90.0, 10.0])
    for f in SAME:
        torch.testing.assert_close(getattr(a, f), getattr(reference, f), atol=1e-5, rtol=0, msg=f)
    assert b.gripper_nodes[:, 0].tolist() == [3, 30]
    only = tmp_path / "nodes.yaml"
    only.write_text(yaml.safe_dump([{"gripper_nodes": [3, 30], "gripper_forces": [1.0, 2.0]}]))
    no_template = AMPNDataModule(str(data_dir), generate=False, predict_file=str(only), min_coarse_nodes=4)
    with pytest.raises(ValueError, match=r"setting 0 lacks field 'gripper_positions'"):
        no_template.setup("predict")
    missing = AMPNDataModule(
        str(data_dir), generate=False, predict_file=str(only), predict_template="none.pt"
    )
    with pytest.raises(
        FileNotFoundError, match=r"none.pt: no such template trajectory \(data.predict_template\)"
    ):
        missing.setup("predict")
