"""Make the committed test fixtures: a tiny simulated dataset and a tiny trained checkpoint.

    python tests/make_fixtures.py   # writes tests/data/tiny/, tests/data/tiny_family*/, tests/data/tiny.ckpt

``tests/data/tiny/``: 2 training, 1 validation and 1 test trajectory of the small simulator
setting (``torch_ampn.testing.SMALL_SIMULATOR``, eager solver). ``tests/data/tiny_family/``:
3/1/2 trajectories of a family of parts of that setting with 2 or 3 plies (two meshes);
``tests/data/tiny_family_deep/``: 2 test parts of that family with deeper domes (55-60 mm), the
extrapolation set of the family benchmark's test.
``tests/data/tiny.ckpt``: the ``last.ckpt`` of a 6-step CLI fit of a d = 16, 2-level model on
the tiny dataset (:func:`fit_config`), the fit the test run makes once (``tiny_fit`` in
``tests/conftest.py``).
``tests/test_fixtures.py`` checks that these functions still make what is committed.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

import yaml

DATA = Path(__file__).parent / "data"
#: The committed datasets and checkpoint.
TINY_DATA, TINY_FAMILY, TINY_CKPT = DATA / "tiny", DATA / "tiny_family", DATA / "tiny.ckpt"
TINY_FAMILY_DEEP = DATA / "tiny_family_deep"
#: Trajectories per split of the tiny dataset, the tiny family dataset and its deep domes.
SPLITS, FAMILY_SPLITS, DEEP_SPLITS = (2, 1, 1), (3, 1, 2), (0, 0, 2)
#: The tiny family: parts of 2 and 3 plies (two meshes), the other ranges the defaults.
FAMILY = {"num_plies": [2, 3]}
#: The deep domes: the family's ranges with the dome depth beyond them.
DEEP = {"dome_depth": [55.0, 60.0]}

#: The network of the tiny fit; ``fast_rollout=False``: its validation, test and predict roll out
#: on the plain path, which needs no compile (the fast path has tests of its own).
SMALL_MODEL: dict[str, Any] = dict(
    hidden_channels=16,
    mlp_channels=16,
    num_levels=2,
    pre_layers=1,
    down_layers=1,
    solve_layers=1,
    post_layers=1,
    up_layers=1,
    fast_rollout=False,
)


def make_dataset(out: Path, shard: tuple[int, int] | None = None) -> None:
    """Simulate the tiny dataset into ``out`` (an empty or missing folder); ``shard``: one part of it."""
    from torch_ampn.sim import StampFormingConfig, generate_dataset
    from torch_ampn.testing import SMALL_SIMULATOR

    config = StampFormingConfig.from_dict(SMALL_SIMULATOR)
    generate_dataset(out, *SPLITS, config=config, workers=1, compile=False, progress=False, shard=shard)


def make_family_dataset(out: Path, shard: tuple[int, int] | None = None) -> None:
    """Simulate the tiny family dataset (:data:`FAMILY`, :data:`FAMILY_SPLITS`) into ``out``."""
    from torch_ampn.sim import PartFamily, StampFormingConfig, generate_dataset
    from torch_ampn.testing import SMALL_SIMULATOR

    config = StampFormingConfig.from_dict(SMALL_SIMULATOR)
    family = PartFamily.from_dict(FAMILY)
    options = dict(workers=1, compile=False, progress=False, shard=shard)
    generate_dataset(out, *FAMILY_SPLITS, config=config, family=family, **options)


def make_family_deep_dataset(out: Path, shard: tuple[int, int] | None = None) -> None:
    """Simulate the deep domes of the tiny family (:data:`DEEP`, :data:`DEEP_SPLITS`) into ``out``."""
    from torch_ampn.sim import PartFamily, StampFormingConfig, generate_dataset
    from torch_ampn.testing import SMALL_SIMULATOR

    config = StampFormingConfig.from_dict(SMALL_SIMULATOR)
    family = PartFamily.from_dict({**PartFamily.from_dict(FAMILY).to_dict(), **DEEP})
    options = dict(workers=1, compile=False, progress=False, shard=shard)
    generate_dataset(out, *DEEP_SPLITS, config=config, family=family, **options)


def fit_config(folder: Path, data_dir: Path) -> tuple[Path, Path]:
    """Write the tiny fit's config to ``folder/tiny.yaml``: ``(config path, output folder)``.

    6 steps, validation at steps 3 and 6, a CSV log of every step (with the learning rate),
    ``last.ckpt`` at every validation, reports under ``out/reports``.
    """
    out = folder / "out"
    config = {
        "seed_everything": 0,
        "trainer": {
            "accelerator": "cpu",
            "devices": 1,
            "max_steps": 6,
            "val_check_interval": 3,
            "check_val_every_n_epoch": None,
            "log_every_n_steps": 1,
            "enable_model_summary": False,
            "enable_progress_bar": False,
            "logger": {
                "class_path": "lightning.pytorch.loggers.CSVLogger",
                "init_args": {"save_dir": str(out), "name": "logs", "version": ""},
            },
            "callbacks": [
                {
                    "class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                    "init_args": {"dirpath": str(out / "ckpt"), "save_last": True},
                },
                {
                    "class_path": "lightning.pytorch.callbacks.LearningRateMonitor",
                    "init_args": {"logging_interval": "step"},
                },
            ],
        },
        "model": {
            **SMALL_MODEL,
            "lr": 1e-3,
            "final_lr": 1e-4,
            "warmup_steps": 2,
            "statistics_samples": 8,
            "output_dir": str(out / "reports"),
        },
        "data": {"data_dir": str(data_dir), "generate": False, "min_coarse_nodes": 4},
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    return path, out


def make_checkpoint(folder: Path, data_dir: Path) -> Path:
    """Run the tiny fit in ``folder`` on ``data_dir``; returns its ``last.ckpt``."""
    from torch_ampn.cli.train import main

    config, out = fit_config(folder, data_dir)
    main(["fit", "--config", str(config)])
    return out / "ckpt" / "last.ckpt"


def main(argv: list[str] | None = None) -> None:
    """Write ``tests/data/tiny/``, ``tests/data/tiny_family*/`` and ``tests/data/tiny.ckpt`` anew."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "tiny"
        make_dataset(data)
        ckpt = make_checkpoint(Path(tmp) / "fit", data)
        shutil.rmtree(data / "cache", ignore_errors=True)  # hierarchies: made again where needed
        shutil.rmtree(TINY_DATA, ignore_errors=True)
        shutil.copytree(data, TINY_DATA)
        shutil.copyfile(ckpt, TINY_CKPT)
        families = ((make_family_dataset, TINY_FAMILY), (make_family_deep_dataset, TINY_FAMILY_DEEP))
        for make, committed in families:
            make(Path(tmp) / committed.name)
            shutil.rmtree(committed, ignore_errors=True)
            shutil.copytree(Path(tmp) / committed.name, committed)
    print(f"wrote {TINY_DATA}, {TINY_FAMILY}, {TINY_FAMILY_DEEP} and {TINY_CKPT}")


if __name__ == "__main__":
    main()
