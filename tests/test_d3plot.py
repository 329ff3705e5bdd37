"""LS-DYNA d3plot exchange: round trips through lasso-python's own writer, fibres, refusals."""

import dataclasses
import math

import numpy as np
import pytest
import torch
import yaml

from torch_ampn.cli import data as data_cli
from torch_ampn.data import Trajectory, TrajectoryFormatError
from torch_ampn.data.d3plot_io import read_d3plot, write_d3plot
from torch_ampn.data.part_map import fibres_from_angle

lasso = pytest.importorskip("lasso.dyna", reason="the d3plot extra (lasso-python) is not installed")
D3plot, A = lasso.D3plot, lasso.ArrayType

FIELDS = [
    "pos",
    "time",
    "component",
    "node_type",
    "fiber",
    "gripper_nodes",
    "gripper_anchor",
    "gripper_force",
]


def assert_same(a: Trajectory, b: Trajectory) -> None:
    for f in FIELDS:
        torch.testing.assert_close(getattr(b, f), getattr(a, f), atol=0, rtol=0, msg=f)
    assert all(torch.equal(x, y) for x, y in zip(a.cells, b.cells, strict=True))
    assert a.names == b.names


def test_round_trip_through_lassos_writer(small_runs, tmp_path):
    traj = small_runs[0]
    path = write_d3plot(traj, tmp_path / "run")
    assert path.name == "d3plot" and (tmp_path / "run" / "parts.yaml").is_file()
    back = read_d3plot(path)
    assert_same(traj, back)  # bit for bit: float32 states, fibres from the plies' angles
    assert back.meta["node_ids"] == list(range(1, traj.num_nodes + 1))
    plain = D3plot(str(path))  # what LS-PrePost reads: the current coordinates of every state
    np.testing.assert_array_equal(plain.arrays[A.node_displacement][-1], traj.pos[-1].numpy())


def test_a_prediction_goes_in_the_states(small_runs, tmp_path):
    traj = small_runs[0]
    predicted = traj.pos + 0.25
    predicted[0] = traj.pos[0]
    back = read_d3plot(write_d3plot(traj, tmp_path / "pred", predicted_pos=predicted))
    torch.testing.assert_close(back.pos, predicted, atol=0, rtol=0)
    with pytest.raises(ValueError, match="predicted_pos has shape"):
        write_d3plot(traj, tmp_path / "bad", predicted_pos=predicted[:2])


def test_fibres_that_vary_go_through_a_csv(small_runs, tmp_path):
    traj = small_runs[0]
    fiber = traj.fiber.clone()
    ply0 = torch.nonzero(traj.component == 0).squeeze(1)
    angle = torch.linspace(0, 1, ply0.numel())
    fiber[ply0] = torch.stack([angle.cos(), angle.sin(), torch.zeros_like(angle)], 1)
    traj = dataclasses.replace(traj, fiber=fiber)
    back = read_d3plot(write_d3plot(traj, tmp_path / "csv"))
    assert (tmp_path / "csv" / "fibres.csv").is_file()
    torch.testing.assert_close(back.fiber, traj.fiber, atol=1e-7, rtol=0)


def test_fibre_angles_by_hand():
    """A unit square in the xy plane, and the same square turned 30 degrees about x."""
    square = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    cells = torch.tensor([[0, 1, 2, 3]])
    x, z = torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64)
    f = fibres_from_angle(square, cells, 30.0, x, z)
    expected = torch.tensor([math.cos(math.pi / 6), math.sin(math.pi / 6), 0.0], dtype=torch.float64)
    torch.testing.assert_close(f, expected.expand(4, 3))
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    tilted = square @ torch.tensor(
        [[1, 0, 0], [0, c, s], [0, -s, c]], dtype=torch.float64
    )  # rows: (x, y c, y s)
    f = fibres_from_angle(tilted, cells.flip(1), 90.0, x, z)  # reversed winding: the normal still faces up
    torch.testing.assert_close(f, torch.tensor([0.0, c, s], dtype=torch.float64).expand(4, 3))


def _parts(path):
    return yaml.safe_load((path.parent / "parts.yaml").read_text())


def _rewrite(path, spec):
    (path.parent / "parts.yaml").write_text(yaml.safe_dump(spec))


def test_bad_part_maps_are_refused_in_one_line(small_runs, tmp_path):
    traj = small_runs[0]
    path = write_d3plot(traj, tmp_path / "run")
    good = _parts(path)
    punch_node = int(torch.nonzero(traj.node_type == 1)[0]) + 1
    cases = [
        (
            {**good, "parts": {k: v for k, v in good["parts"].items() if k != 6}},
            r"leaves parts \[6\] .* unassigned",
        ),
        ({**good, "parts": {**good["parts"], 9: {"type": "die"}}}, r"parts \[9\] have no cells"),
        ({**good, "parts": {**good["parts"], 5: {"type": "tool"}}}, r"'parts.5.type' must be one of"),
        (
            {
                **good,
                "grippers": [
                    {**good["grippers"][0], "nodes": [punch_node, *good["grippers"][0]["nodes"][1:]]}
                ],
            },
            rf"'grippers\[0\].nodes': node id {punch_node} is not a node of a ply",
        ),
        (
            {**good, "grippers": [{**good["grippers"][0], "nodes": good["grippers"][0]["nodes"][:1]}]},
            r"one node per ply needed",
        ),
        (
            {**good, "parts": {**good["parts"], 1: {"type": "ply"}}},
            r"'parts.1': a ply needs fiber_angle, or fiber_file rows",
        ),
    ]
    for spec, message in cases:
        _rewrite(path, spec)
        with pytest.raises(TrajectoryFormatError, match=message) as err:
            read_d3plot(path)
        assert "parts.yaml" in str(err.value) and "\n" not in str(err.value)


def _tiny_plot(**extra):
    """Two shells of parts 1 and 2 sharing no node, two states (the current coordinates)."""
    plot = D3plot()
    coords = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [5, 0, 1], [6, 0, 1], [6, 1, 1], [5, 1, 1]], np.float32
    )
    plot.arrays[A.node_coordinates] = coords
    plot.arrays[A.node_ids] = np.arange(1, 8, dtype=np.int32)
    plot.arrays[A.node_displacement] = np.stack([coords, coords + 0.5])
    plot.arrays[A.global_timesteps] = np.array([0.0, 1.0], np.float32)
    plot.arrays[A.element_shell_node_indexes] = np.array([[0, 1, 2, 2], [3, 4, 5, 6]], np.int32)
    plot.arrays[A.element_shell_part_indexes] = np.array([0, 1], np.int32)
    plot.arrays[A.element_shell_ids] = np.array([1, 2], np.int32)
    plot.arrays[A.part_ids] = np.array([1, 2], np.int32)
    plot.arrays.update(extra)
    return plot


TINY_MAP = {"parts": {1: {"type": "ply", "fiber_angle": 0}, 2: {"type": "punch"}}}


def test_a_d3plot_of_our_own_making(tmp_path):
    """Written with lasso directly (not by write_d3plot): a triangle ply and a quad punch."""
    _tiny_plot().write_d3plot(str(tmp_path / "d3plot"))
    traj = read_d3plot(tmp_path / "d3plot", TINY_MAP)
    assert [c.tolist() for c in traj.cells] == [[[0, 1, 2]], [[3, 4, 5, 6]]]
    assert traj.node_type.tolist() == [0, 0, 0, 1, 1, 1, 1] and traj.names == ["part1", "part2"]
    torch.testing.assert_close(traj.pos[1] - traj.pos[0], torch.full((7, 3), 0.5))
    torch.testing.assert_close(traj.fiber[:3], torch.tensor([[1.0, 0, 0]]).expand(3, 3))


def test_a_d3plot_whose_parts_have_titles_only(tmp_path):
    """lasso then reads ``part_titles_ids`` and no ``part_ids``: the ids come from the titles section."""
    plot = _tiny_plot()
    del plot.arrays[A.part_ids]
    plot.arrays[A.part_titles_ids] = np.array([7, 3], np.int32)  # internal order: part 7, then part 3
    plot.arrays[A.part_titles] = np.array([b"ply".ljust(72), b"punch".ljust(72)])
    plot.write_d3plot(str(tmp_path / "d3plot"))
    assert A.part_ids not in D3plot(str(tmp_path / "d3plot")).arrays
    spec = {"parts": {7: {"type": "ply", "fiber_angle": 0}, 3: {"type": "punch"}}}
    traj = read_d3plot(tmp_path / "d3plot", spec)
    assert traj.names == ["ply", "punch"] and traj.node_type.tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert [c.tolist() for c in traj.cells] == [[[0, 1, 2]], [[3, 4, 5, 6]]]


def test_unsupported_d3plots_are_refused_in_one_line(tmp_path):
    shared = _tiny_plot()
    shared.arrays[A.element_shell_node_indexes] = np.array([[0, 1, 2, 2], [2, 4, 5, 6]], np.int32)
    no_states = _tiny_plot()
    del no_states.arrays[A.node_displacement], no_states.arrays[A.global_timesteps]
    solid = _tiny_plot()
    solid.arrays[A.element_solid_node_indexes] = np.array([[0, 1, 2, 3, 4, 5, 6, 6]], np.int32)
    solid.arrays[A.element_solid_part_indexes] = np.array([0], np.int32)
    solid.arrays[A.element_solid_ids] = np.array([9], np.int32)
    eroded = _tiny_plot()
    eroded.arrays[A.element_shell_is_alive] = np.array([[1, 1], [1, 0]], np.float32)
    no_ids = _tiny_plot()
    del no_ids.arrays[A.part_ids]
    for name, plot, message in [
        ("solid", solid, r"field 'element_solid_node_indexes': 1 solid or thick-shell elements"),
        ("eroded", eroded, r"field 'element_shell_is_alive': 1 shell elements are deleted"),
        ("shared", shared, r"node id 3 belongs to parts 1 and 2"),
        ("no_ids", no_ids, r"field 'part_ids': the d3plot names no part ids"),
        (
            "no_states",
            no_states,
            r"field 'node_displacement': the d3plot holds nodal displacements for 0 states",
        ),
    ]:
        (tmp_path / name).mkdir()
        plot.write_d3plot(str(tmp_path / name / "d3plot"))
        with pytest.raises(TrajectoryFormatError, match=message) as err:
            read_d3plot(tmp_path / name / "d3plot", TINY_MAP)
        assert str(tmp_path / name / "d3plot") in str(err.value) and "\n" not in str(err.value)


def test_convert_and_export_d3plot_on_the_command_line(small_runs, tmp_path, capsys):
    src = tmp_path / "traj.pt"
    small_runs[1].save(src)
    assert data_cli.main(["export", str(src), "--out", str(tmp_path / "run"), "--format", "d3plot"]) == 0
    assert data_cli.main(["convert", str(tmp_path / "run"), "--out", str(tmp_path / "back.pt")]) == 0
    assert_same(small_runs[1], Trajectory.load(tmp_path / "back.pt"))
    other = tmp_path / "elsewhere.yaml"
    other.write_text(yaml.safe_dump({"parts": {1: {"type": "ply"}}}))
    capsys.readouterr()
    argv = [
        "convert",
        str(tmp_path / "run" / "d3plot"),
        "--parts",
        str(other),
        "--out",
        str(tmp_path / "x.pt"),
    ]
    assert data_cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "elsewhere.yaml: field 'parts' leaves parts [2, 3" in err and "\n" not in err
    assert not (tmp_path / "x.pt").exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert data_cli.main(["export", str(src), "--out", str(tmp_path / "mine"), "--format", "d3plot"]) == 2
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"  # never replaced
