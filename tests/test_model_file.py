"""Model files: torch-ampn export writes one from a checkpoint; AMPNSurrogate.load reads it, no Lightning."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torch_ampn.data import HierarchyCache, Trajectory
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.rollout import rollout

pytest.importorskip("lightning")

DATA = Path(__file__).parent / "data"
TINY_CKPT = DATA / "tiny.ckpt"


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    from torch_ampn.cli.export import main

    return main([str(TINY_CKPT), str(tmp_path_factory.mktemp("model") / "model.pt")])


def _rollout(surrogate):
    traj = Trajectory.load(sorted((DATA / "tiny" / "test").glob("*.pt"))[0])
    hierarchy = HierarchyCache(None, max_levels=surrogate.num_levels)(traj)
    return rollout(
        surrogate, traj, hierarchy, fast=True, generator=torch.Generator().manual_seed(0), compile=False
    )


def test_a_model_file_rolls_out_as_its_checkpoint_does(model_file):
    from torch_ampn.training import NextStepLightningModule

    module = NextStepLightningModule.load_from_checkpoint(TINY_CKPT, map_location="cpu").eval()
    loaded = AMPNSurrogate.load(model_file)
    assert not loaded.training and loaded.statistics_frozen
    assert loaded.meta["training_meshes"] == module._training_meshes
    for (name, a), (_, b) in zip(
        module.surrogate.state_dict().items(), loaded.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    from torch_ampn.forming import load_surrogate

    assert torch.equal(_rollout(load_surrogate(model_file)), _rollout(loaded))  # any kind: the file names it
    assert torch.equal(_rollout(loaded), _rollout(module.surrogate))
    # a plain torch file: arguments as JSON text, the weights as tensors
    payload = torch.load(model_file, weights_only=True)
    assert payload["format"] == "torch-ampn surrogate" and isinstance(payload["arguments"], str)


ROLLOUT_WITHOUT_LIGHTNING = """
import sys, torch
from pathlib import Path
from torch_ampn.data import HierarchyCache, Trajectory
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.rollout import rollout
surrogate = AMPNSurrogate.load(sys.argv[1])
traj = Trajectory.load(sorted(Path(sys.argv[2]).glob("*.pt"))[0])
hierarchy = HierarchyCache(None, max_levels=surrogate.num_levels)(traj)
generator = torch.Generator().manual_seed(0)
pred = rollout(surrogate, traj, hierarchy, fast=True, generator=generator, compile=False)
torch.save(pred, sys.argv[3])
print("lightning" in sys.modules)
"""


def test_loading_and_rolling_out_import_no_lightning(model_file, tmp_path):
    out = tmp_path / "pred.pt"
    args = [str(model_file), str(DATA / "tiny" / "test"), str(out)]
    run = subprocess.run(
        [sys.executable, "-c", ROLLOUT_WITHOUT_LIGHTNING, *args], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().splitlines()[-1] == "False"
    assert torch.equal(torch.load(out, weights_only=True), _rollout(AMPNSurrogate.load(model_file)))


def test_what_is_not_a_model_file_is_refused_in_one_line(model_file, tmp_path):
    payload = torch.load(model_file, weights_only=True)
    cases = {
        "junk.pt": (b"\x00garbage", "not a readable torch-ampn model file"),
        "checkpoint.pt": (TINY_CKPT.read_bytes(), "not a torch-ampn model file (field 'format')"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
            AMPNSurrogate.load(tmp_path / name)
        assert str(tmp_path / name) in str(err.value) and "\n" not in str(err.value)
    wrong = {**payload, "state_dict": {k: v for k, v in payload["state_dict"].items() if "decoder" not in k}}
    torch.save(wrong, tmp_path / "wrong.pt")
    with pytest.raises(ValueError, match=r"field 'state_dict' does not fit the arguments"):
        AMPNSurrogate.load(tmp_path / "wrong.pt")
