"""The committed fixtures are what tests/make_fixtures.py makes today."""

import inspect
import json

import pytest
import torch

pytest.importorskip("lightning")

from make_fixtures import (  # noqa: E402
    DEEP_SPLITS,
    FAMILY_SPLITS,
    SPLITS,
    TINY_CKPT,
    TINY_DATA,
    TINY_FAMILY,
    TINY_FAMILY_DEEP,
    make_dataset,
    make_family_dataset,
    make_family_deep_dataset,
)

from torch_ampn.data import Trajectory  # noqa: E402


@pytest.mark.slow
@pytest.mark.parametrize(
    "make, committed_dir, splits",
    [
        (make_dataset, TINY_DATA, SPLITS),
        (make_family_dataset, TINY_FAMILY, FAMILY_SPLITS),
        (make_family_deep_dataset, TINY_FAMILY_DEEP, DEEP_SPLITS),
    ],
    ids=["tiny", "tiny_family", "tiny_family_deep"],
)
def test_the_script_still_simulates_the_committed_dataset(tmp_path, make, committed_dir, splits):
    # One of two shards: a shard makes the same files as the whole job (generate_dataset's contract,
    # tested in test_data_cli.py). The family's parts are simulated one by one, so half of them check
    # the script in half the time; the tiny dataset is one chunk of 4 and is made whole.
    folder = tmp_path / "made"
    make(folder, shard=(0, 2))
    made = sorted(p.relative_to(folder) for p in folder.glob("*/*.pt"))
    committed = sorted(p.relative_to(committed_dir) for p in committed_dir.glob("*/*.pt"))
    assert len(committed) == sum(splits) and made and set(made) <= set(committed)
    assert json.loads((folder / "dataset.json").read_text()) == json.loads(
        (committed_dir / "dataset.json").read_text()
    )
    for name in made:
        a, b = Trajectory.load(folder / name), Trajectory.load(committed_dir / name)
        energy_a, energy_b = a.meta.pop("energy"), b.meta.pop("energy")  # [T] per term
        assert a.meta == b.meta and a.names == b.names, name
        for field in ("component", "node_type", "gripper_nodes", "gripper_force", "time", "fiber"):
            assert torch.equal(getattr(a, field), getattr(b, field)), (name, field)
        # The eager solver repeats itself to rounding on one CPU. Other CPUs round other ways, and
        # the plies' contact amplifies those differences (chaos): on an Intel Xeon the fixtures
        # made on an AMD EPYC agree to float32 up to saved step 2 and differ by up to 10 mm at the end.
        # So the first half of the steps (the plies have moved 17-22 mm by then) is compared to
        # rounding, and the whole forming to a few percent of the motion.
        early = a.pos.size(0) // 2
        torch.testing.assert_close(a.pos[:early], b.pos[:early], rtol=0, atol=1e-4, msg=str(name))
        assert float((a.pos[early - 1] - a.pos[0]).abs().max()) > 1.0  # the plies move: a real comparison
        assert energy_a.keys() == energy_b.keys(), name
        for term in energy_a:
            ea, eb = (torch.tensor(e[term][:early], dtype=torch.float64) for e in (energy_a, energy_b))
            torch.testing.assert_close(ea, eb, rtol=1e-6, atol=1e-9, msg=f"{name}: energy {term}")
        motion = (b.pos[-1] - b.pos[0]).double().pow(2).sum(-1).mean().sqrt()  # RMS, mm
        final_gap = (a.pos[-1] - b.pos[-1]).double().pow(2).sum(-1).mean().sqrt()
        assert final_gap < 0.1 * motion, (name, float(final_gap), float(motion))


@pytest.mark.xdist_group("tiny_fit")
def test_the_runs_fit_reproduces_the_committed_checkpoint(tiny_fit):
    """The run's one fit (``tiny_fit``: the script's fit on the committed data) gives the committed weights.

    Its config is ``make_fixtures.fit_config``."""
    _, out = tiny_fit
    made = torch.load(out / "ckpt" / "last.ckpt", weights_only=True)
    committed = torch.load(TINY_CKPT, weights_only=True)
    assert made["global_step"] == committed["global_step"] == 6
    paths = {"output_dir", "data_dir"}  # where the fit ran
    from torch_ampn.training import AMPNDataModule, NextStepLightningModule
    from torch_ampn.training.checkpoint import module_arguments, module_defaults

    model = NextStepLightningModule
    # the committed checkpoint predates the split into one module per model: its other model's
    # arguments and its mode are dropped as load_module drops them; Lightning's own keys are not ours
    made["hyper_parameters"] = {k: v for k, v in made["hyper_parameters"].items() if not k.startswith("_")}
    committed["hyper_parameters"] = module_arguments(committed["hyper_parameters"], model)
    classes = {
        "hyper_parameters": module_defaults(model),
        "datamodule_hyper_parameters": {
            n: p.default for n, p in inspect.signature(AMPNDataModule).parameters.items()
        },
    }
    for key, defaults in classes.items():
        # options added after the fixture was written must be at their defaults (same behaviour)
        added = {k: v for k, v in made[key].items() if k not in committed[key]}
        assert added == {k: defaults[k] for k in added}, key
        assert {k: v for k, v in made[key].items() if k not in paths | added.keys()} == {
            k: v for k, v in committed[key].items() if k not in paths
        }, key
    assert made["state_dict"].keys() == committed["state_dict"].keys()
    for name, value in committed["state_dict"].items():
        # bit for bit on the CPU that wrote it (same thread count); rounding elsewhere
        torch.testing.assert_close(made["state_dict"][name], value, rtol=1e-4, atol=1e-5, msg=name)
