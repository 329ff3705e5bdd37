"""Two-process CPU DDP (gloo) through the CLI: statistics, validation and test, each trajectory once."""

import csv
import os
import socket
import subprocess
import sys

import pytest
import torch
import yaml

pytest.importorskip("lightning")

from torch_ampn.rollout import rollout_rmse  # noqa: E402
from torch_ampn.training import AMPNDataModule, NextStepLightningModule  # noqa: E402

MODEL = dict(
    hidden_channels=8, mlp_channels=8, num_levels=2, pre_layers=1, down_layers=1, solve_layers=1,
    post_layers=1, up_layers=1, contact_radius=12.0, contact_k=1, warmup_steps=1, statistics_samples=8,
    touch_radii=[3.0], fast_rollout=False,
)  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(*args, cwd):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port())}
    done = subprocess.run(
        [sys.executable, "-m", "torch_ampn.cli.train", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done


#: The DDP dataset: 3/3/3 trajectories (odd counts, which a 2-rank DistributedSampler would pad
#: with a repeat) copied from the 4 of the committed tiny dataset under new names.
DDP_SPLITS = {
    "train": ["train/traj_000000", "train/traj_000001", "val/traj_100000"],
    "val": ["val/traj_100000", "test/traj_200000", "train/traj_000000"],
    "test": ["test/traj_200000", "val/traj_100000", "train/traj_000001"],
}
FIRST_FILE = {"train": 0, "val": 100000, "test": 200000}


def _ddp_dataset(folder, tiny_data):
    """:data:`DDP_SPLITS` in ``folder``: what is checked (statistics, each trajectory once) needs
    names, not new physics, so nothing is simulated."""
    import shutil

    for split, sources in DDP_SPLITS.items():
        (folder / split).mkdir(parents=True)
        for i, source in enumerate(sources):
            name = f"traj_{FIRST_FILE[split] + i:06d}.pt"
            shutil.copyfile(tiny_data / f"{source}.pt", folder / split / name)
    shutil.copyfile(tiny_data / "dataset.json", folder / "dataset.json")


#: Both tests read the one DDP run (two CLI subprocesses of two ranks each): one xdist worker makes it.
ddp_group = pytest.mark.xdist_group("ddp_run")


@pytest.fixture(scope="module")
def ddp_run(tmp_path_factory, tiny_data):
    root = tmp_path_factory.mktemp("ddp")
    _ddp_dataset(root / "data", tiny_data)
    out = root / "out"
    config = {
        "seed_everything": 0,
        "trainer": {
            "accelerator": "cpu", "devices": 2, "strategy": "ddp", "max_steps": 4, "val_check_interval": 4,
            "check_val_every_n_epoch": None, "num_sanity_val_steps": 0, "enable_progress_bar": False,
            "enable_model_summary": False,
            "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger",
                       "init_args": {"save_dir": str(out), "name": "logs", "version": ""}},
            "callbacks": [{"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                           "init_args": {"dirpath": str(out / "ckpt"), "save_last": True}}],
        },
        "model": {**MODEL, "output_dir": str(out / "reports")},
        "data": {"data_dir": str(root / "data"), "generate": False, "min_coarse_nodes": 4, "batch_size": 2},
    }  # fmt: skip
    path = root / "ddp.yaml"
    path.write_text(yaml.safe_dump(config))
    _cli("fit", "--config", str(path), cwd=root)
    with open(out / "logs" / "metrics.csv") as f:  # before `test` writes its own metrics there
        logged = [float(r["val/rollout_rmse"]) for r in csv.DictReader(f) if r.get("val/rollout_rmse")]
    _cli("test", "--config", str(path), "--ckpt_path", str(out / "ckpt" / "last.ckpt"), cwd=root)
    return root, out, logged


@pytest.mark.slow
@ddp_group
def test_ddp_fit_uses_the_single_process_statistics_and_validates_every_trajectory_once(ddp_run):
    root, out, logged = ddp_run
    module = NextStepLightningModule.load_from_checkpoint(out / "ckpt" / "last.ckpt", map_location="cpu")
    contact = dict(contact_radius=12.0, contact_k=1)
    dm = AMPNDataModule(str(root / "data"), generate=False, min_coarse_nodes=4, max_levels=2, **contact)
    dm.setup("fit")
    single = NextStepLightningModule(**MODEL)
    single.fit_statistics(dm.statistics_samples(8))
    for (
        name,
        buffer,
    ) in single.surrogate.named_buffers():  # the normalisation statistics of rank 0 = one process
        torch.testing.assert_close(module.surrogate.get_buffer(name), buffer, rtol=0, atol=0, msg=name)
    # the logged validation RMSE is the mean over all 3 validation trajectories, each once (a 2-rank
    # DistributedSampler would repeat one), recomputed here in one process from the same weights
    items = dm._rollout_split("val")
    assert len(items) == 3
    values = []
    for i in range(len(items)):
        item = items[i]
        pred, _ = module.rollout_item(item)
        values.append(float(rollout_rmse(pred, item.trajectory.pos, item.trajectory.ply_mask)[1:].mean()))
    assert logged[-1] == pytest.approx(sum(values) / 3, rel=1e-5)


@pytest.mark.slow
@ddp_group
def test_ddp_test_reports_every_trajectory_once_with_one_figure(ddp_run):
    _, out, _ = ddp_run
    with open(out / "reports" / "test_rmse.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["trajectory"] for r in rows] == ["traj_200000", "traj_200001", "traj_200002"]
    assert sorted(p.name for p in (out / "reports").glob("final_shape_*.png")) == [
        "final_shape_traj_200000.png"
    ]
    assert len(list((out / "reports" / "xdmf").glob("*.xdmf"))) == 3
