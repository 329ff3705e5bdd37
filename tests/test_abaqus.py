"""Abaqus runs: a flat deck (meshio) and the ODB export's table -> trajectory; the script on a fake ODB."""

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import meshio
import numpy as np
import pytest
import torch
import yaml

from torch_ampn.cli import data as data_cli
from torch_ampn.data import Trajectory, TrajectoryFormatError
from torch_ampn.data.abaqus_io import merged_node_blocks, node_labels, read_abaqus

ROOT = Path(__file__).resolve().parents[1]
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


def _script():
    spec = importlib.util.spec_from_file_location(
        "abaqus_odb_export", ROOT / "scripts" / "abaqus_odb_export.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class FakeOdb:
    """What the script reads of ``odbAccess.openOdb(...)``: instances' node labels, steps, frames, U."""

    def __init__(self, instances: dict, steps: dict):
        self.rootAssembly = SimpleNamespace(instances=instances)
        self.steps = steps
        self.closed = False

    def close(self):
        self.closed = True


def _frame(value, labels, u):
    values = [SimpleNamespace(nodeLabel=int(n), data=tuple(row)) for n, row in zip(labels, u, strict=True)]
    return SimpleNamespace(frameValue=value, fieldOutputs={"U": SimpleNamespace(values=values)})


def _odb_of(traj: Trajectory, split: int = 3) -> FakeOdb:
    """One instance with labels 1..N; the states in two steps (the second starts where the first ends)."""
    labels = np.arange(1, traj.num_nodes + 1)
    u = (traj.pos.double() - traj.pos[0].double()).numpy()
    t = traj.time.double().numpy()
    first = SimpleNamespace(totalTime=0.0, frames=[_frame(t[k], labels, u[k]) for k in range(split + 1)])
    second = SimpleNamespace(
        totalTime=t[split], frames=[_frame(t[k] - t[split], labels, u[k]) for k in range(split, len(t))]
    )
    instance = SimpleNamespace(nodes=[SimpleNamespace(label=int(n)) for n in labels])
    return FakeOdb({"PART-1-1": instance}, {"Draping": first, "Forming": second})


def _deck(traj: Trajectory, path: Path) -> dict:
    """A flat deck of ``traj``'s initial mesh, one element set per component; returns its part map."""
    blocks, sets, count = [], {}, 0
    for c, cells in enumerate(traj.cells):
        kind = "triangle" if cells.size(1) == 3 else "quad"
        blocks.append((kind, cells.numpy()))
        sets[traj.names[c].upper()] = [
            np.arange(len(cells)) if i == c else np.array([], dtype=int) for i in range(len(traj.cells))
        ]
        count += len(cells)
    meshio.write(
        path, meshio.Mesh(traj.pos[0].double().numpy(), blocks, cell_sets=sets), file_format="abaqus"
    )
    kinds = {0: "ply", 1: "punch", 2: "die"}
    angles = [0.0, 45.0, 90.0, -45.0]
    parts = {}
    for c, name in enumerate(traj.names):
        role = {"type": kinds[int(traj.node_type[traj.component == c][0])], "name": name}
        if role["type"] == "ply":
            role["fiber_angle"] = angles[c]
        parts[name.upper()] = role
    grippers = [
        {"nodes": (traj.gripper_nodes[g] + 1).tolist(), "anchor": traj.gripper_anchor[g].tolist(),
         "force": float(traj.gripper_force[g])}
        for g in range(traj.num_grippers)
    ]  # fmt: skip
    return {"parts": parts, "grippers": grippers}


@pytest.fixture
def run(small_runs, tmp_path):
    """``forming.inp``, ``forming.npz`` (the script on a stand-in ODB), ``parts.yaml`` of a simulated run."""
    traj = small_runs[0]
    spec = _deck(traj, tmp_path / "forming.inp")
    (tmp_path / "parts.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    odb = _odb_of(traj)
    frames = _script().export("forming.odb", str(tmp_path / "forming.npz"), open_odb=lambda p, readOnly: odb)
    assert frames == traj.num_steps + 1 and odb.closed
    return traj, tmp_path


def test_deck_and_odb_table_give_the_trajectory_back(run):
    traj, folder = run
    back = read_abaqus(folder / "forming.inp")  # the table and the part map beside the deck
    for f in FIELDS:
        torch.testing.assert_close(getattr(back, f), getattr(traj, f), atol=2e-5, rtol=0, msg=f)
    assert all(torch.equal(a, b) for a, b in zip(back.cells, traj.cells, strict=True))
    assert back.names == traj.names and back.meta["node_ids"] == list(range(1, traj.num_nodes + 1))


def test_the_scripts_table_by_hand(small_runs, tmp_path):
    """Two steps: the second's first frame is left out, times add up, 2D U is padded, no U gives zero."""
    labels = [7, 3]
    steps = {
        "A": SimpleNamespace(totalTime=0.0, frames=[_frame(0.0, labels, [(0, 0), (0, 0)]),
                                                    _frame(0.5, labels, [(1, 2), (3, 4)])]),
        "B": SimpleNamespace(totalTime=0.5, frames=[_frame(0.0, labels, [(1, 2), (3, 4)]),
                                                    SimpleNamespace(frameValue=0.25, fieldOutputs={})]),
    }  # fmt: skip
    odb = FakeOdb({"I": SimpleNamespace(nodes=[SimpleNamespace(label=n) for n in labels])}, steps)
    out = tmp_path / "t.npz"
    assert _script().export("x.odb", str(out), open_odb=lambda p, readOnly: odb) == 3
    table = np.load(out)
    assert sorted(table.files) == ["node_labels", "time", "u"]
    assert table["node_labels"].tolist() == [7, 3] and table["time"].tolist() == [0.0, 0.5, 0.75]
    assert table["u"].tolist() == [[[0, 0, 0], [0, 0, 0]], [[1, 2, 0], [3, 4, 0]], [[0, 0, 0], [0, 0, 0]]]
    twice = FakeOdb({"I": odb.rootAssembly.instances["I"], "J": odb.rootAssembly.instances["I"]}, steps)
    with pytest.raises(SystemExit, match="node labels repeat across instances"):
        _script().export("x.odb", str(out), open_odb=lambda p, readOnly: twice)
    with pytest.raises(SystemExit, match="no step 'C'"):
        _script().export("x.odb", str(out), ["C"], open_odb=lambda p, readOnly: odb)


def test_node_labels_of_a_deck_with_comments_and_two_node_blocks(tmp_path):
    deck = tmp_path / "d.inp"
    deck.write_text("*Heading\n** a comment\n*Node\n10, 0, 0, 0\n12, 1, 0, 0\n*NODE, NSET=B\n 5, 0, 1, 0\n"
                    "*Element, type=S3, elset=P\n1, 10, 12, 5\n*Node Output\nU\n")  # fmt: skip
    assert node_labels(deck).tolist() == [10, 12, 5]
    merged = tmp_path / "m.inp"
    merged.write_text(merged_node_blocks(deck.read_text()))  # meshio 5.3 keeps the last block only
    mesh = meshio.read(merged, file_format="abaqus")
    np.testing.assert_array_equal(mesh.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])  # in the file's order
    np.testing.assert_array_equal(mesh.cells[0].data, [[0, 1, 2]])


def test_bad_abaqus_input_is_refused_in_one_line(run):
    traj, folder = run
    deck, table = folder / "forming.inp", folder / "forming.npz"
    spec = yaml.safe_load((folder / "parts.yaml").read_text())
    text = deck.read_text()
    data = dict(np.load(table))
    cases = []
    (folder / "instance.inp").write_text(
        text.replace("*HEADING", "*HEADING\n*Instance, name=PLY-1, part=PLY")
    )
    cases.append((dict(inp=folder / "instance.inp", displacements=table), r"field '\*Instance'"))
    less = {k: v for k, v in spec["parts"].items() if k != "DIE"}
    cases.append(
        (
            dict(inp=deck, part_map={**spec, "parts": less}),
            r"leaves \d+ shell elements .* no mapped element set",
        )
    )
    np.savez(
        folder / "short.npz", **{**data, "node_labels": data["node_labels"][:-1], "u": data["u"][:, :-1]}
    )
    cases.append(
        (dict(inp=deck, displacements=folder / "short.npz"), r"field 'node_labels': 1 nodes of the deck")
    )
    np.savez(folder / "no_u.npz", node_labels=data["node_labels"], time=data["time"])
    cases.append((dict(inp=deck, displacements=folder / "no_u.npz"), r"field 'u' is missing"))
    solid = text + "*ELEMENT, TYPE=C3D8\n9999,1,2,3,4,5,6,7,8\n"
    (folder / "solid.inp").write_text(solid)
    cases.append((dict(inp=folder / "solid.inp", displacements=table), r"elements of type 'hexahedron'"))
    for kwargs, message in cases:
        with pytest.raises(TrajectoryFormatError, match=message) as err:
            read_abaqus(**kwargs)
        assert "\n" not in str(err.value)
    with pytest.raises(FileNotFoundError, match="abaqus_odb_export.py"):
        read_abaqus(deck, folder / "none.npz")


def test_convert_an_abaqus_run_on_the_command_line(run, capsys):
    traj, folder = run
    out = folder / "run0.pt"
    argv = ["convert", str(folder / "forming.inp"), "--parts", str(folder / "parts.yaml"), "--out", str(out)]
    assert data_cli.main(argv) == 0
    torch.testing.assert_close(Trajectory.load(out).pos, traj.pos, atol=2e-5, rtol=0)
    capsys.readouterr()
    assert data_cli.main([*argv[:2], "--displacements", str(folder / "none.npz"), "--out", str(out)]) == 2
    assert "none.npz: no such displacement table" in capsys.readouterr().err
