import dataclasses
import json
from pathlib import Path

import pytest
import torch

from torch_ampn.cli import data as data_cli
from torch_ampn.data import Trajectory
from torch_ampn.data.dataset import split_files
from torch_ampn.sim import StampFormingConfig, generate_dataset
from torch_ampn.sim import dataset as dataset_module

# A quarter of the stroke in a quarter of the time: the same punch speed, a quarter of the solver's
# substeps (132). These tests check files, shards and threads, not the forming.
TINY = StampFormingConfig(
    ply_cells=4, punch_cells=(3, 3), die_cells=(3, 3), num_steps=4, duration=0.25, stroke=15.0
)
DATA = Path(__file__).parent / "data" / "tiny"


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

    spec_written = (tmp_path / "dataset.json").stat().st_mtime_ns
    calls = []
    real = dataset_module._simulate_chunk
    monkeypatch.setattr(dataset_module, "_simulate_chunk", lambda job: calls.append(job[1]) or real(job))
    generate_dataset(tmp_path, 2, 1, 1, workers=1, batch=2, compile=False, progress=False, config=TINY)
    assert calls == []  # everything exists: nothing simulated again
    # ... and nothing written: processes sharing a complete folder do not race on dataset.json
    assert (tmp_path / "dataset.json").stat().st_mtime_ns == spec_written
    paths[1].write_bytes(b"truncated")
    kept = paths[0].stat().st_mtime_ns
    generate_dataset(tmp_path, 2, 1, 1, workers=1, batch=2, compile=False, progress=False, config=TINY)
    assert calls == [[("train", 0), ("train", 1)]]  # the broken file's chunk, simulated whole ...
    assert paths[0].stat().st_mtime_ns == kept  # ... but only the missing file is written
    assert torch.equal(Trajectory.load(paths[1]).pos, trajs[1].pos)  # deterministic regeneration


def test_blow_up_flags_a_node_carried_past_the_tools_or_jumping_within_a_step():
    """Hand cases on a simulated trajectory: its own motion is healthy; a moved ply node is not."""
    from torch_ampn.sim.spread import blow_up

    traj = Trajectory.load(dataset_module.trajectory_path(DATA, "train", 0))
    assert blow_up(traj) is None
    travel = float((traj.pos - traj.pos[0])[:, ~traj.ply_mask].norm(dim=-1).max())  # 60 mm
    plies = torch.nonzero(traj.ply_mask).flatten()
    node = int(plies[(traj.pos[:, plies] - traj.pos[0, plies]).norm(dim=-1).max(0).values.argmin()])
    far = traj.pos.clone()
    far[-1, node] = far[0, node] + torch.tensor([0.0, 0.0, -1.3 * travel])  # 1.3 x the travel, at the end
    assert "ends 78 mm from its start" in blow_up(_with_pos(traj, far))
    # 6 saved steps: the punch moves 10 mm in each, so a node may move 0.5 x 60 + 10 = 40 mm in one
    jump = traj.pos.clone()
    jump[2:, node] += torch.tensor([0.8 * travel, 0.0, 0.0])  # 48 mm in one step, 48 + its own in all
    assert "moves 48 mm within one saved step" in blow_up(_with_pos(traj, jump))
    jump = traj.pos.clone()
    jump[2:, node] += torch.tensor([0.6 * travel, 0.0, 0.0])  # 36 mm: within 40 mm
    assert blow_up(_with_pos(traj, jump)) is None


def _with_pos(traj: Trajectory, pos: torch.Tensor) -> Trajectory:
    d = traj.to_dict()
    d["pos"] = pos
    return Trajectory.from_dict(d)


def test_generate_sets_blown_up_runs_aside_and_does_not_simulate_them_again(tmp_path, monkeypatch):
    """A run flagged by blow_up goes to <split>/failed/ with its reason, outside the split, once."""
    real_check = dataset_module.blow_up
    flag_seed_1 = lambda traj: "blown up (test)" if traj.meta["seed"] == 1 else real_check(traj)  # noqa: E731
    monkeypatch.setattr(dataset_module, "blow_up", flag_seed_1)
    paths = generate_dataset(
        tmp_path, 2, 0, 0, workers=1, batch=2, compile=False, progress=False, config=TINY
    )
    assert [p.name for p in paths] == ["traj_000000.pt"]
    aside = Trajectory.load(tmp_path / "train" / "failed" / "traj_000001.pt")
    assert aside.meta["failed"] == "blown up (test)" and aside.meta["seed"] == 1
    assert [p.name for p in split_files(tmp_path, "train")] == ["traj_000000.pt"]
    calls = []
    real = dataset_module._simulate_chunk
    monkeypatch.setattr(dataset_module, "_simulate_chunk", lambda job: calls.append(job[1]) or real(job))
    generate_dataset(tmp_path, 2, 0, 0, workers=1, batch=2, compile=False, progress=False, config=TINY)
    assert calls == []  # the set-aside run counts as done
    # a dataset made before the check: its blown-up file is moved aside on the next generate
    monkeypatch.setattr(dataset_module, "blow_up", lambda traj: "old" if traj.meta["seed"] == 0 else None)
    paths = generate_dataset(
        tmp_path, 2, 0, 0, workers=1, batch=2, compile=False, progress=False, config=TINY
    )
    assert paths == [] and calls == []
    assert Trajectory.load(tmp_path / "train" / "failed" / "traj_000000.pt").meta["failed"] == "old"


def test_generate_refuses_other_settings_in_same_folder(tmp_path):
    generate_dataset(tmp_path, 1, 0, 0, workers=1, compile=False, progress=False, config=TINY)
    other = dataclasses.replace(TINY, ply_cells=5)
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
    options = {"compile": False, "device": "cpu", "family": None, "config": None}
    assert calls == [(tmp_path, (1, 0, 0, "coarse", 1, 2), options)]
    assert f"1 trajectories in {tmp_path}" in capsys.readouterr().out
    # --simulator: inline JSON or a file override the resolution's settings
    assert data_cli.main([*argv, "--simulator", '{"shear_stiffness": 2.0}']) == 0
    assert calls[-1][2]["config"] == StampFormingConfig(shear_stiffness=2.0)
    (tmp_path / "soft.yaml").write_text("shear_stiffness: 2.0\ndamping: 5.0\n")
    assert data_cli.main([*argv, "--resolution", "paper", "--simulator", str(tmp_path / "soft.yaml")]) == 0
    assert calls[-1][2]["config"] == StampFormingConfig.paper(shear_stiffness=2.0, damping=5.0)

    def refuse(*args, **kwargs):
        raise ValueError(f"{tmp_path}/dataset.json: the folder holds a dataset made with other settings")

    monkeypatch.setattr(data_cli, "generate_dataset", refuse)
    assert data_cli.main(argv) == 2
    assert "dataset.json: the folder holds" in capsys.readouterr().err


def test_convert_and_export_commands(tmp_path, capsys):
    job = (TINY.to_dict(), [("train", 7)], [True], str(tmp_path), False, "cpu")
    traj = dataset_module._simulate_chunk(job)
    src = tmp_path / "train" / "traj_000007.pt"
    assert traj == [str(src)]
    assert data_cli.main(["export", str(src), "--out", str(tmp_path / "x" / "t.xdmf")]) == 0
    assert data_cli.main(["convert", str(tmp_path / "x" / "t.xdmf"), "--out", str(tmp_path / "back.pt")]) == 0
    a, b = Trajectory.load(src), Trajectory.load(tmp_path / "back.pt")
    assert torch.allclose(a.pos, b.pos, atol=1e-4) and a.names == b.names
    assert torch.equal(a.gripper_nodes, b.gripper_nodes)
    assert data_cli.main(["convert", str(tmp_path / "missing.xdmf"), "--out", str(tmp_path / "y.pt")]) == 2
    assert "missing.xdmf" in capsys.readouterr().err


@pytest.mark.slow
def test_shards_in_any_order_make_the_files_of_one_job(tmp_path):
    sizes = (5, 1, 2)  # 8 jobs in chunks of 2: shard i of 3 takes chunks i, i + 3
    options = dict(workers=1, batch=2, compile=False, progress=False, config=TINY)
    one, sharded = tmp_path / "one", tmp_path / "sharded"
    names = [p.relative_to(one) for p in generate_dataset(one, *sizes, **options)]
    parts = {i: generate_dataset(sharded, *sizes, **options, shard=(i, 3)) for i in (2, 0, 1)}
    assert sorted(p.relative_to(sharded) for part in parts.values() for p in part) == sorted(names)
    assert not set(parts[0]) & set(parts[1]) and not set(parts[1]) & set(parts[2])  # disjoint
    expected = ["traj_000000.pt", "traj_000001.pt", "traj_200000.pt", "traj_200001.pt"]
    assert [p.name for p in parts[0]] == expected
    for name in [*names, "dataset.json"]:
        assert (one / name).read_bytes() == (sharded / name).read_bytes(), name
    # rerunning a shard completes it, with the same bytes
    (sharded / names[3]).unlink()
    generate_dataset(sharded, *sizes, **options, shard=(1, 3))
    assert (one / names[3]).read_bytes() == (sharded / names[3]).read_bytes()
    with pytest.raises(ValueError, match="shard must be i/n"):
        generate_dataset(tmp_path / "x", 1, 0, 0, config=TINY, shard=(3, 3))
    with pytest.raises(SystemExit):
        data_cli.main(["generate", "--out", str(tmp_path / "x"), "--shard", "1of2"])


def test_check_summarises_a_dataset_and_names_its_problems(tmp_path, capsys):
    options = dict(workers=1, batch=2, compile=False, progress=False, config=TINY)
    paths = generate_dataset(tmp_path / "ds", 2, 1, 1, **options)
    assert data_cli.main(["check", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    assert "train       2       1" in out and "OK" in out
    paths[1].write_bytes(b"truncated")  # a broken file ...
    other = dataclasses.replace(TINY, ply_cells=5)
    generate_dataset(tmp_path / "other", 0, 0, 1, **{**options, "config": other})
    extra = tmp_path / "ds" / "test" / "traj_999999.pt"  # ... and a test file of another mesh
    extra.write_bytes((tmp_path / "other" / "test" / "traj_200000.pt").read_bytes())
    assert data_cli.main(["check", str(tmp_path / "ds")]) == 1
    captured = capsys.readouterr()
    assert f"problem: {paths[1]}" in captured.err
    assert "test: 2 different meshes (1 like traj_200000.pt; 1 like traj_999999.pt)" in captured.err
    assert "2 problem(s)" in captured.out
    assert data_cli.main(["check", str(tmp_path / "empty")]) == 1
    assert "no trajectory files" in capsys.readouterr().err


def test_generate_refuses_bad_simulator_settings_in_one_line(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("shear_stifness: 2.0\n")
    for spec, where in [("{not json", "--simulator {not json"), (str(tmp_path / "bad.yaml"), "bad.yaml")]:
        assert data_cli.main(["generate", "--out", str(tmp_path / "ds"), "--simulator", spec]) == 2
        err = capsys.readouterr().err.strip()
        assert where in err and "not simulator settings" in err and "\n" not in err, err
    assert "unknown setting(s) 'shear_stifness'" in err
    assert not (tmp_path / "ds").exists()


def test_generate_refuses_a_device_it_cannot_use_in_one_line(tmp_path, capsys):
    cases = ["nonsense"] + ([] if torch.cuda.is_available() else ["cuda"])
    for device in cases:
        assert data_cli.main(["generate", "--out", str(tmp_path / "ds"), "--device", device]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("torch-ampn-data: error: --device") and "\n" not in err, err
    assert not (tmp_path / "ds").exists()  # refused before anything was written


@pytest.mark.slow
def test_generate_in_processes_writes_the_same_files_as_in_process(tmp_path):
    options = dict(batch=1, compile=False, progress=False, config=TINY)
    alone = generate_dataset(tmp_path / "alone", 2, 1, 0, workers=1, **options)
    pooled = generate_dataset(tmp_path / "pooled", 2, 1, 0, workers=2, **options)
    assert [p.relative_to(tmp_path / "pooled") for p in pooled] == [
        p.relative_to(tmp_path / "alone") for p in alone
    ]
    for a, b in zip(alone, pooled, strict=True):
        ta, tb = Trajectory.load(a).to_dict(), Trajectory.load(b).to_dict()
        for key, value in ta.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, tb[key]), (a.name, key)


@pytest.mark.slow
def test_generate_from_a_script_without_main_guard_fails_in_one_line_instead_of_hanging(tmp_path):
    import subprocess
    import sys

    script = tmp_path / "gen.py"
    script.write_text(
        "from pathlib import Path\n"
        "from torch_ampn.sim import StampFormingConfig, generate_dataset\n"
        "cfg = StampFormingConfig(ply_cells=4, punch_cells=(3, 3), die_cells=(3, 3), num_steps=4,\n"
        "                         duration=0.25, stroke=15.0)\n"
        "options = dict(workers=2, batch=1, compile=False, progress=False, config=cfg)\n"
        "generate_dataset(Path('ds'), 2, 0, 0, **options)\n"
    )
    run = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert run.returncode != 0
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("RuntimeError: generate_dataset: a worker process died")
    assert 'if __name__ == "__main__":' in last


def test_energy_command_prints_plots_and_refuses_data_without_a_balance(tmp_path, capsys):
    from torch_ampn.sim import simulate_batch

    (tmp_path / "data" / "train").mkdir(parents=True)
    for t in simulate_batch(TINY, seeds=[0, 1]):
        t.save(tmp_path / "data" / "train" / f"traj_{t.meta['seed']:06d}.pt")
    plot, out = tmp_path / "energy.png", tmp_path / "energy.json"
    code = data_cli.main(["energy", str(tmp_path / "data"), "--plot", str(plot), "--json", str(out)])
    assert code == 0 and plot.read_bytes()[:4] == b"\x89PNG"
    table = json.loads(out.read_text())
    assert set(table) == {"traj_000000.pt", "traj_000001.pt"}
    saved = Trajectory.load(tmp_path / "data" / "train" / "traj_000000.pt").meta["energy"]
    assert table["traj_000000.pt"]["final"]["work_punch"] == pytest.approx(saved["work_punch"][-1])
    assert "KE/IE" in capsys.readouterr().out
    # a run of another solver (or simulated before the balance was kept) has none
    traj = Trajectory.load(split_files(DATA, "train")[0])
    old = tmp_path / "old.pt"
    Trajectory.from_dict(
        {**traj.to_dict(), "meta": {k: v for k, v in traj.meta.items() if k != "energy"}}
    ).save(old)
    assert data_cli.main(["energy", str(old)]) == 2
    assert f"{old}: field 'meta' has no 'energy'" in capsys.readouterr().err


def test_every_chunk_is_simulated_on_one_thread_whatever_the_callers_count(tmp_path, monkeypatch):
    """A trajectory's last bits depend on the thread count of its (compiled) reductions: in process
    (one worker, or one shard's one chunk) a chunk runs on one thread, as in a worker process, and
    the caller's count comes back afterwards. Two thread counts of the caller make the same bytes."""
    seen = []
    real = dataset_module.simulate_batch

    def recording(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset_module, "simulate_batch", recording)
    options = dict(workers=1, batch=1, compile=False, progress=False, config=TINY)
    before = torch.get_num_threads()
    try:
        for threads, folder in ((2, "two"), (1, "one")):
            torch.set_num_threads(threads)
            generate_dataset(tmp_path / folder, 2, 0, 0, **options)
            assert torch.get_num_threads() == threads  # restored
    finally:
        torch.set_num_threads(before)
    assert seen == [1, 1, 1, 1]
    for name in ("train/traj_000000.pt", "train/traj_000001.pt"):
        assert (tmp_path / "two" / name).read_bytes() == (tmp_path / "one" / name).read_bytes(), name
