import pytest
import torch

from torch_ampn import data_cli
from torch_ampn.data import Trajectory
from torch_ampn.sim import StampFormingConfig, generate_dataset
from torch_ampn.sim import dataset as dataset_module

TINY = StampFormingConfig(ply_cells=4, punch_cells=(3, 3), die_cells=(3, 3), num_steps=4)


def test_generate_is_resumable_and_replaces_broken_files(tmp_path, monkeypatch):
    paths = generate_dataset(
        tmp_path, 2, 1, 1, workers=1, batch=2, compile=False, progress=False, config=TINY
    )
    assert [p.relative_to(tmp_path).as_posix() for p in paths] == [
        "train/traj_000000.pt",
        "train/traj_000001.pt",
        "val/traj_100000.pt",
        "test/traj_200000.pt",
    ]
    trajs = [Trajectory.load(p) for p in paths]
    assert trajs[0].num_steps == 4 and trajs[0].meta["seed"] == 0
    assert not torch.equal(trajs[0].gripper_force, trajs[1].gripper_force)
    assert (tmp_path / "dataset.json").exists()

    calls = []
    real = dataset_module._simulate_chunk
    monkeypatch.setattr(dataset_module, "_simulate_chunk", lambda job: calls.append(job[1]) or real(job))
    generate_dataset(tmp_path, 2, 1, 1, workers=1, compile=False, progress=False, config=TINY)
    assert calls == []  # everything exists: nothing simulated again
    paths[1].write_bytes(b"truncated")
    generate_dataset(tmp_path, 2, 1, 1, workers=1, compile=False, progress=False, config=TINY)
    assert calls == [[("train", 1)]]
    assert torch.equal(Trajectory.load(paths[1]).pos, trajs[1].pos)  # deterministic regeneration


def test_generate_refuses_other_settings_in_same_folder(tmp_path):
    generate_dataset(tmp_path, 1, 0, 0, workers=1, compile=False, progress=False, config=TINY)
    other = StampFormingConfig(ply_cells=5, punch_cells=(3, 3), die_cells=(3, 3), num_steps=4)
    with pytest.raises(ValueError, match="other simulator settings"):
        generate_dataset(tmp_path, 1, 0, 0, workers=1, compile=False, progress=False, config=other)


def test_generate_command_calls_generate_dataset(tmp_path, monkeypatch, capsys):
    calls = []

    def fake(out, *args, **kwargs):
        calls.append((out, args, kwargs))
        return [out / "train" / "traj_000000.pt"]

    monkeypatch.setattr(data_cli, "generate_dataset", fake)
    argv = ["generate", "--out", str(tmp_path), "--num-train", "1", "--num-val", "0", "--num-test", "0"]
    assert data_cli.main([*argv, "--workers", "1", "--batch", "2", "--no-compile"]) == 0
    assert calls == [(tmp_path, (1, 0, 0, "coarse", 1, 2), {"compile": False})]
    assert f"1 trajectories in {tmp_path}" in capsys.readouterr().out

    def refuse(*args, **kwargs):
        raise ValueError(f"{tmp_path}/dataset.json: the folder holds a dataset made with other settings")

    monkeypatch.setattr(data_cli, "generate_dataset", refuse)
    assert data_cli.main(argv) == 2
    assert "dataset.json: the folder holds" in capsys.readouterr().err


def test_convert_and_export_commands(tmp_path, capsys):
    traj = dataset_module._simulate_chunk((TINY.to_dict(), [("train", 7)], str(tmp_path), False))
    src = tmp_path / "train" / "traj_000007.pt"
    assert traj == [str(src)]
    assert data_cli.main(["export", str(src), "--out", str(tmp_path / "x" / "t.xdmf")]) == 0
    assert data_cli.main(["convert", str(tmp_path / "x" / "t.xdmf"), "--out", str(tmp_path / "back.pt")]) == 0
    a, b = Trajectory.load(src), Trajectory.load(tmp_path / "back.pt")
    assert torch.allclose(a.pos, b.pos, atol=1e-4) and a.names == b.names
    assert torch.equal(a.gripper_nodes, b.gripper_nodes)
    assert data_cli.main(["convert", str(tmp_path / "missing.xdmf"), "--out", str(tmp_path / "y.pt")]) == 2
    assert "missing.xdmf" in capsys.readouterr().err
