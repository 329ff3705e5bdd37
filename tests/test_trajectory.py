"""Trajectory file format and meshio round trips; corrupt input is refused with file and field named."""

import json

import pytest
import torch

from torch_ampn.data import Trajectory, TrajectoryFormatError
from torch_ampn.data.meshio_io import (
    export_vtu_series,
    export_xdmf,
    read_time_series,
    read_vtu_series,
    read_xdmf,
)
from torch_ampn.testing import small_trajectory


def assert_same(a: Trajectory, b: Trajectory, atol: float = 0.0) -> None:
    assert torch.allclose(a.pos, b.pos, atol=atol, rtol=0)
    assert torch.allclose(a.time, b.time)
    assert len(a.cells) == len(b.cells)
    for ca, cb in zip(a.cells, b.cells, strict=True):
        assert torch.equal(ca, cb)
    for name in ("component", "node_type", "gripper_nodes"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    for name in ("fiber", "gripper_anchor", "gripper_force"):
        assert torch.allclose(getattr(a, name), getattr(b, name)), name
    assert a.names == b.names


def test_save_load_round_trip(tmp_path):
    traj = small_trajectory()
    traj.save(tmp_path / "t.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["t.pt"]
    back = Trajectory.load(tmp_path / "t.pt")
    assert_same(traj, back)
    assert back.meta == {"seed": 0}


def test_derived_quantities_by_hand():
    traj = small_trajectory()
    assert traj.num_steps == 4 and traj.num_components == 3 and traj.num_grippers == 1
    g = traj.gripper_positions()
    assert torch.allclose(g[2, 0], 0.5 * (traj.pos[2, 3] + traj.pos[2, 15]))
    f = traj.gripper_force_vectors()
    d = traj.gripper_anchor[0] - g[1, 0]
    assert torch.allclose(f[1, 0], 42.0 * d / d.norm())
    assert torch.allclose(traj.displacement()[0], torch.zeros(traj.num_nodes, 3))


@pytest.mark.parametrize("kind", ["xdmf", "vtu"])
def test_meshio_export_then_convert_back(tmp_path, kind):
    traj = small_trajectory()
    if kind == "xdmf":
        path = export_xdmf(traj, tmp_path / "t.xdmf")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["t.h5", "t.meta.json", "t.xdmf"]
        back = read_xdmf(path)
    else:
        folder = export_vtu_series(traj, tmp_path / "series")
        assert len(list(folder.glob("*.vtu"))) == traj.num_steps + 1
        back = read_vtu_series(folder)
    assert_same(traj, back, atol=1e-5)
    assert_same(traj, read_time_series(tmp_path / ("t.xdmf" if kind == "xdmf" else "series")), atol=1e-5)


def test_export_with_prediction_has_error_field(tmp_path):
    import meshio

    traj = small_trajectory()
    pred = traj.pos.clone()
    pred[:, 0, 2] += torch.arange(traj.num_steps + 1).float()  # error grows by 1 mm per step at node 0
    export_xdmf(traj, tmp_path / "p.xdmf", predicted_pos=pred)
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "p.xdmf")) as reader:
        reader.read_points_cells()
        _, point_data, _ = reader.read_data(3)
    assert point_data["error"][0] == pytest.approx(3.0)
    assert abs(point_data["error"][1:]).max() == 0.0
    assert point_data["predicted_displacement"].shape == (traj.num_nodes, 3)


def test_missing_series_fields_are_named(tmp_path):
    import meshio

    traj = small_trajectory()
    folder = tmp_path / "bad"
    folder.mkdir()
    for k in range(3):
        m = meshio.Mesh(
            traj.pos[0].numpy(),
            [("triangle", traj.cells[0].numpy())],
            point_data={"component": traj.component.numpy()},
        )
        m.write(folder / f"s{k}.vtu")
    with pytest.raises(TrajectoryFormatError, match=r"bad: missing point data field 'node_type'"):
        read_vtu_series(folder)


def _corrupt(d: dict, field: str, value) -> dict:
    d = dict(d)
    if value is KeyError:
        del d[field]
    else:
        d[field] = value
    return d


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("pos", KeyError, "missing field.*'pos'"),
        ("gripper_force", KeyError, "missing field.*'gripper_force'"),
        ("pos", "nan", "'pos' contains NaN"),
        ("pos", "2d", "'pos' must have 3 dimensions"),
        ("time", torch.linspace(0, 1, 3), "'time' has 3 steps but 'pos' has 5"),
        ("time", torch.tensor([0.0, 0.2, 0.1, 0.5, 1.0]), "'time' must be strictly increasing"),
        ("component", torch.zeros(3, dtype=torch.long), "'component' has 3 entries"),
        ("node_type", "float", "'node_type' must be an integer tensor"),
        ("node_type", "unknown", "'node_type' contains unknown type 7"),
        ("fiber", torch.zeros(5, 3), "'fiber' must have shape"),
        ("cells", "out_of_range", r"'cells\[0\]' references nodes outside"),
        ("cells", "empty_component", "component 1 .'ply1'. has no nodes"),
        ("gripper_anchor", torch.zeros(2, 3), "'gripper_anchor' must have shape"),
        ("gripper_nodes", torch.tensor([[3, 30]]), "'gripper_nodes' must reference ply nodes"),
        ("format", "something", "'format' must be"),
    ],
)
def test_corrupt_files_are_refused_naming_file_and_field(tmp_path, field, value, match):
    traj = small_trajectory()
    d = traj.to_dict()
    if value == "nan":
        value = d["pos"].clone()
        value[2, 5, 1] = float("nan")
    elif value == "2d":
        value = d["pos"][0]
    elif value == "float":
        value = d["node_type"].float()
    elif value == "unknown":
        value = d["node_type"].clone()
        value[0] = 7
    elif value == "out_of_range":
        value = [c.clone() for c in d["cells"]]
        value[0][0, 0] = 999
    elif value == "empty_component":
        # every node of component 1 relabelled as component 0; its cells now reference them
        comp = d["component"].clone()
        comp[comp == 1] = 0
        d["component"] = comp
        value = d["cells"]
    path = tmp_path / "bad.pt"
    torch.save(_corrupt(d, field, value), path)
    with pytest.raises(TrajectoryFormatError, match=match) as err:
        Trajectory.load(path)
    assert str(path) in str(err.value)


def test_unreadable_file_and_missing_file(tmp_path):
    path = tmp_path / "junk.pt"
    path.write_bytes(b"\x00garbage")
    with pytest.raises(TrajectoryFormatError, match="junk.pt: not a readable trajectory file"):
        Trajectory.load(path)
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        Trajectory.load(tmp_path / "nope.pt")


def test_save_refuses_invalid_and_leaves_nothing(tmp_path):
    traj = small_trajectory()
    traj.pos[1, 0, 0] = float("inf")
    with pytest.raises(TrajectoryFormatError, match="'pos' contains NaN or infinite"):
        traj.save(tmp_path / "t.pt")
    assert list(tmp_path.iterdir()) == []


def test_meta_json_errors_are_named(tmp_path):
    traj = small_trajectory()
    export_xdmf(traj, tmp_path / "t.xdmf")
    (tmp_path / "t.meta.json").write_text(json.dumps({"gripper_nodes": [[1]], "gripper_anchor": "x"}))
    with pytest.raises(TrajectoryFormatError, match="t.meta.json: invalid metadata file"):
        read_xdmf(tmp_path / "t.xdmf")
