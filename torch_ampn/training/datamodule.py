"""AMPNDataModule: the dataset folder (made by the embedded simulator when empty) as Lightning dataloaders."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader as TorchDataLoader

from torch_ampn.baselines.prior import fitted_prior, make_prior, out_of_fold_priors
from torch_ampn.data.dataset import (
    DirectDataset,
    HierarchyCache,
    StepDataset,
    TrajectoryDataset,
    file_topology_key,
    split_files,
    topology_key,
)
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.family import PartFamily
from torch_ampn.training.items import (
    EachOnceSampler,
    ResumableLoader,
    ResumableShuffleSampler,
    RolloutDataset,
    identity_collate,
    list_collate,
)
from torch_ampn.training.predict_settings import read_settings
from torch_ampn.transforms.contact import ComponentRadiusGraph
from torch_ampn.utils.imports import import_object


class AMPNDataModule(L.LightningDataModule):
    """Training windows and whole trajectories of a dataset folder.

    Layout: ``<data_dir>/{train,val,test}/*.pt`` (see :mod:`torch_ampn.data.trajectory`). With
    ``generate=True`` the missing trajectories of the requested split sizes are made first, by
    default with the embedded simulator (``torch-ampn-data generate``, progress bar, parallel,
    resumable; ``make_dataset`` puts another source in its place), so an empty folder becomes
    the default dataset.

    * ``fit``: :class:`~torch_ampn.data.StepDataset` windows with contact edges
      (:class:`~torch_ampn.transforms.ComponentRadiusGraph`), batched by PyG's ``DataLoader``;
      validation yields whole trajectories (one :class:`~torch_ampn.training.items.RolloutItem`
      per batch) for rollouts.
    * ``test``: whole test trajectories.
    * ``predict``: new process settings, from ``predict_file`` (JSON or YAML: a list of
      ``{"gripper_positions": [...], "gripper_forces": [...]}``, optional ``"name"``) or from
      ``predict_gripper_positions`` / ``predict_gripper_forces``; the tools and the mesh are
      those of the dataset's simulator settings (``dataset.json``), or, with
      ``predict_template``, those of a trajectory of one's own part (a converted solver run),
      where a setting may also give ``gripper_nodes`` instead of ``gripper_positions``
      (:func:`~torch_ampn.data.template.template_settings`).

    Args:
        data_dir: Dataset folder.
        num_train: Training trajectories to generate (when ``generate``).
        num_val: Validation trajectories to generate.
        num_test: Test trajectories to generate.
        resolution: ``"coarse"`` or ``"paper"`` (simulator resolution when generating).
        simulator: Overrides of :class:`~torch_ampn.sim.StampFormingConfig` fields for generating
            (e.g. ``{"ply_cells": 24}``), applied on top of ``resolution``.
        generate: Simulate missing trajectories in ``prepare_data``.
        generate_workers: Processes for generating (default: CPU cores).
        generate_compile: Compile the simulator's step when generating (pays off from a few
            coarse trajectories on; a handful of tiny ones are quicker eager).
        batch_size: Training windows per batch (paper: 1).
        num_workers: Dataloader worker processes for training windows.
        max_levels: Hierarchy levels (linked to the model's ``num_levels`` by the CLI).
        min_coarse_nodes: Stop coarsening below this many nodes.
        contact_radius: Contact radius of training windows (linked to the model's).
        contact_k: Contact neighbours per other component (linked to the model's).
        contact_mode: Contact edge mode (linked to the model's; see
            :class:`~torch_ampn.transforms.ComponentRadiusGraph`).
        contact_positions: Positions the contact edges are built from (linked to the model's).
        limit_val_trajectories: Use only the first ones of the validation split (rollouts are costly).
        cache_windows: Keep the training windows with their contact edges in memory after the
            first epoch (:class:`~torch_ampn.data.StepDataset`'s ``cache_samples``); saves the
            contact search of every later epoch, costs memory (~60 kB per window on the coarse
            default mesh, 2.4 MB on the paper's: about 82 GB for its 684 training
            trajectories, so leave it off there), per data-loader worker.
        trajectory_cache_mb: Memory for loaded trajectories per split and process (the least
            recently used are dropped and read again when needed); ``None``: keep all.
        predict_file: Process settings to predict (JSON/YAML list).
        predict_gripper_positions: Or: one list of gripper edge fractions per setting.
        predict_gripper_forces: And: one list of gripper forces (N) per setting.
        predict_template: A trajectory file (``.pt``) of one's own part whose mesh, components,
            fibres and tool motion the predicted settings take (``None``: the embedded simulator's
            part of ``dataset.json``).
        predict_batch_size: Settings rolled out together by ``predict`` (one batch on the fast
            path, :class:`~torch_ampn.rollout.fast.FastRollout`; outputs per setting as with 1).
        family: Generate a family of parts (:class:`~torch_ampn.sim.PartFamily` settings, or
            ``"default"``): every trajectory its own tool geometry and ply stack; pair it with
            ``model.component_encoding: stack``.
        prior: A setting-aware baseline whose trajectory every trajectory carries as its
            :attr:`~torch_ampn.data.Trajectory.prior` (for ``model.prior_features``; one of
            :data:`~torch_ampn.baselines.prior.PRIOR_NAMES`, e.g. ``"pod_gp"``): out of fold on the
            training split (``prior_folds`` folds), fitted on the whole training split for the
            others and for predict; ``None``: no prior.
        prior_folds: Folds of the training split's out-of-fold priors.
        make_dataset: What makes the missing trajectories when ``generate``: a function
            ``(folder, num_train, num_val, num_test) -> None`` (or its import path
            ``"package.module:name"``, as configs give it) that writes
            ``<folder>/{train,val,test}/*.pt`` trajectories (e.g. runs one's own solver and
            converts its output); ``None``: the embedded simulator (:meth:`simulate_dataset`).
        shuffle_seed: Seed of the training windows' order (a permutation per epoch, see
            :class:`~torch_ampn.training.items.ResumableShuffleSampler`); ``None``: the fit's
            ``seed_everything`` value (0 without one). A fit resumed from a checkpoint continues
            the stopped epoch's order where it stopped.
        mode: ``"next_step"``: training windows; ``"direct"``: one sample per training trajectory
            (:class:`~torch_ampn.data.DirectDataset`, kept in memory) for a direct model (linked
            to the model's ``mode`` by the CLI).
        bundle_steps: Steps a training window's target spans (a next-step model's temporal
            bundling, :func:`~torch_ampn.data.step_sample`; linked to the model's by the CLI).
    """

    def __init__(
        self,
        data_dir: str = "data/default",
        num_train: int = 24,
        num_val: int = 2,
        num_test: int = 4,
        resolution: str = "coarse",
        simulator: dict[str, Any] | None = None,
        generate: bool = True,
        generate_workers: int | None = None,
        generate_compile: bool = True,
        batch_size: int = 1,
        num_workers: int = 0,
        max_levels: int = 4,
        min_coarse_nodes: int = 16,
        contact_radius: float = 3.0,
        contact_k: int = 3,
        contact_mode: str = "component_knn",
        contact_positions: str = "current",
        limit_val_trajectories: int | None = None,
        cache_windows: bool = False,
        trajectory_cache_mb: float | None = 2048.0,
        predict_file: str | None = None,
        predict_gripper_positions: list[list[float]] | None = None,
        predict_gripper_forces: list[list[float]] | None = None,
        predict_batch_size: int = 1,
        predict_template: str | None = None,
        shuffle_seed: int | None = None,
        family: dict[str, Any] | str | None = None,
        prior: str | None = None,
        prior_folds: int = 5,
        make_dataset: str | Callable[..., Any] | None = None,
        mode: str = "next_step",
        bundle_steps: int = 1,
    ) -> None:
        super().__init__()
        if mode not in ("next_step", "direct"):
            raise ValueError(f"data.mode must be 'next_step' or 'direct', got {mode!r}")
        if bundle_steps < 1:
            raise ValueError(f"data.bundle_steps must be >= 1, got {bundle_steps}")
        if predict_batch_size < 1:
            raise ValueError(f"data.predict_batch_size must be >= 1, got {predict_batch_size}")
        # a function object is not a checkpoint's plain value: only its import path is kept
        self.save_hyperparameters(ignore=["make_dataset"] if callable(make_dataset) else None)
        self._make_dataset = (
            import_object(make_dataset, "data.make_dataset")
            if isinstance(make_dataset, str)
            else make_dataset
        )
        if self._make_dataset is not None and not callable(self._make_dataset):
            raise ValueError(f"data.make_dataset: {make_dataset!r} is not callable")
        self.data_dir = Path(data_dir)
        self.contact = ComponentRadiusGraph(
            r=contact_radius, k=contact_k, mode=contact_mode, positions=contact_positions
        )
        self.hierarchies = HierarchyCache(
            self.data_dir / "cache", max_levels=max_levels, min_coarse_nodes=min_coarse_nodes
        )
        self.train_dataset: StepDataset | None = None
        self._splits: dict[str, RolloutDataset] = {}
        self._prior_baseline: Any = None  # the prior fitted on the whole training split
        if prior is not None:
            make_prior(prior)  # a readable error for an unknown name, before any work

    # ---- data on disk ------------------------------------------------------------------------
    def prepare_data(self) -> None:
        """Make the missing trajectories (``generate=True``), or check that the folder has data."""
        hp = self.hparams
        if hp.generate:
            make = self._make_dataset or self.simulate_dataset
            make(self.data_dir, hp.num_train, hp.num_val, hp.num_test)
            return
        if not any(split_files(self.data_dir, s) for s in ("train", "val", "test")):
            raise FileNotFoundError(
                f"{self.data_dir}: no trajectories; set data.generate=true to simulate the default dataset"
            )

    def simulate_dataset(self, folder: Path, num_train: int, num_val: int, num_test: int) -> None:
        """The default ``make_dataset``: the embedded simulator with this module's settings.

        ``resolution``, ``simulator``, ``family``, ``generate_workers`` and ``generate_compile``
        apply; existing valid trajectories are kept (:func:`~torch_ampn.sim.generate_dataset`).
        """
        from torch_ampn.sim.dataset import generate_dataset

        hp = self.hparams
        generate_dataset(
            folder, num_train, num_val, num_test, resolution=hp.resolution, workers=hp.generate_workers,
            compile=hp.get("generate_compile", True), config=self._generator_config(), family=self._family(),
        )  # fmt: skip

    def _family(self) -> PartFamily | None:
        spec = self.hparams.family
        if spec is None:
            return None
        if spec == "default":
            return PartFamily()
        try:
            return PartFamily.from_dict(spec)
        except (TypeError, ValueError) as err:
            raise ValueError(f"data.family: not a family of parts ({err})") from err

    def _generator_config(self) -> StampFormingConfig | None:
        overrides = self.hparams.simulator
        if not overrides:
            return None
        base = StampFormingConfig.paper() if self.hparams.resolution == "paper" else StampFormingConfig()
        try:
            cfg = StampFormingConfig.from_dict(overrides, base=base)
            cfg.validate()
        except (TypeError, ValueError) as err:
            raise ValueError(f"data.simulator: invalid simulator settings {overrides} ({err})") from err
        return cfg

    def simulator_config(self) -> StampFormingConfig:
        """The simulator settings the dataset was made with (``dataset.json``; default if absent)."""
        spec = self.data_dir / "dataset.json"
        if not spec.exists():
            return StampFormingConfig()
        try:
            return StampFormingConfig.from_dict(json.loads(spec.read_text())["simulator"])
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(
                f"{spec}: field 'simulator' is not a valid simulator configuration ({err})"
            ) from err

    # ---- stages ---------------------------------------------------------------------------------
    def _rollout_split(self, split: str, limit: int | None = None) -> RolloutDataset:
        trajectories = TrajectoryDataset(
            self.data_dir, split, max_cached_mb=self.hparams.trajectory_cache_mb, priors=self._priors(split)
        )
        count = len(trajectories) if limit is None else min(limit, len(trajectories))
        names = [f.stem for f in trajectories.files[:count]]
        return RolloutDataset(names, trajectories.__getitem__, self.hierarchies)

    def setup(self, stage: str) -> None:
        """Open the splits the stage needs."""
        hp = self.hparams
        if stage == "fit":
            dataset = DirectDataset if hp.get("mode", "next_step") == "direct" else StepDataset
            self.train_dataset = dataset(
                self.data_dir,
                "train",
                max_levels=hp.max_levels,
                min_coarse_nodes=hp.min_coarse_nodes,
                transform=self.contact,
                cache_samples=hp.cache_windows or hp.get("mode") == "direct",  # one per trajectory
                max_cached_mb=hp.trajectory_cache_mb,
                priors=self._priors("train"),
                bundle_steps=hp.get("bundle_steps", 1),  # 1 for a direct model, whose samples ignore it
            )
        if stage in ("fit", "validate"):
            self._splits["val"] = self._rollout_split("val", hp.limit_val_trajectories)
        if stage == "test":
            self._splits["test"] = self._rollout_split("test")
        if stage == "predict":
            self._splits["predict"] = self._predict_split()

    # ---- priors ---------------------------------------------------------------------------------
    def _priors(self, split: str) -> dict[str, Tensor] | None:
        """File stem -> prior of every trajectory of ``split`` (``None`` without ``prior``)."""
        name = self.hparams.get("prior")
        if name is None:
            return None
        trajectories = TrajectoryDataset(self.data_dir, split, max_cached_mb=0)
        stems = [f.stem for f in trajectories.files]
        if split == "train":
            print(f"prior {name}: out of {self.hparams.prior_folds} folds on the training split")
            priors = out_of_fold_priors(name, list(trajectories), self.hparams.prior_folds, progress=True)
        else:
            baseline = self.prior_baseline()
            priors = [baseline.predict(traj) for traj in trajectories]
        return dict(zip(stems, priors, strict=True))

    def prior_baseline(self) -> Any:
        """The ``prior`` baseline fitted on the whole training split (fitted once, on first use)."""
        if self._prior_baseline is None:
            trajectories = self.training_trajectories()
            if not trajectories:
                raise FileNotFoundError(
                    f"{self.data_dir / 'train'}: data.prior {self.hparams.prior!r} is fitted on the "
                    "training split, which has no trajectories"
                )
            self._prior_baseline = fitted_prior(self.hparams.prior, trajectories)
        return self._prior_baseline

    def fitted_baselines(self) -> dict[str, Any]:
        """The baselines this data module has fitted on the training split so far, by name (its prior)."""
        if self._prior_baseline is None:
            return {}
        return {self.hparams.prior: self._prior_baseline}

    def training_trajectories(self) -> list[Trajectory]:
        """Every trajectory of the training split (for the setting-aware baselines of ``test``)."""
        if not split_files(self.data_dir, "train"):
            return []
        return list(TrajectoryDataset(self.data_dir, "train", max_cached_mb=0))

    def _predict_split(self) -> RolloutDataset:
        from torch_ampn.data.template import template_settings
        from torch_ampn.sim.simulate import process_trajectory

        settings, source = self._predict_settings()
        template = self._predict_template()
        cfg = self.simulator_config() if template is None else None
        names = [s.get("name") or f"setting_{i:03d}" for i, s in enumerate(settings)]
        trajectories = []
        for i, s in enumerate(settings):  # all checked before the first rollout
            try:
                if template is None:
                    traj = process_trajectory(cfg, s["gripper_positions"], s["gripper_forces"])
                else:
                    traj = template_settings(
                        template, s["gripper_forces"], s.get("gripper_positions"), s.get("gripper_nodes")
                    )
                trajectories.append(traj)
            except (TypeError, ValueError) as err:
                raise ValueError(f"{source}: setting {i} ({names[i]}): {err}") from None
        if self.hparams.get("prior") is not None:
            for traj in trajectories:
                traj.prior = self.prior_baseline().predict(traj)
        return RolloutDataset(names, trajectories.__getitem__, self.hierarchies)

    def _predict_template(self) -> Trajectory | None:
        path = self.hparams.get("predict_template")
        if path is None:
            return None
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: no such template trajectory (data.predict_template)")
        return Trajectory.load(path)

    def predict_settings(self) -> list[dict[str, Any]]:
        """The process settings to predict, checked (errors name the file and the field)."""
        return self._predict_settings()[0]

    def _predict_settings(self) -> tuple[list[dict[str, Any]], str]:
        """``(settings, source)``, by :func:`~torch_ampn.training.predict_settings.read_settings`."""
        hp = self.hparams
        template = bool(hp.get("predict_template"))
        return read_settings(
            hp.predict_file, hp.predict_gripper_positions, hp.predict_gripper_forces, template
        )

    # ---- dataloaders ----------------------------------------------------------------------------
    def train_dataloader(self) -> ResumableLoader:
        """Shuffled training windows (PyG batches of :class:`HierarchicalData`)."""
        assert self.train_dataset is not None, "call setup('fit') first"
        workers = self.hparams.num_workers
        seed = self.hparams.shuffle_seed
        if seed is None:  # the fit's seed_everything value, the same on every rank
            seed = int(os.environ.get("PL_GLOBAL_SEED", 0))
        sampler = ResumableShuffleSampler(self.train_dataset, self.hparams.batch_size, seed=seed)
        return ResumableLoader(
            self.train_dataset,
            sampler,
            self._batches_trained,
            num_workers=workers,
            persistent_workers=workers > 0,
        )

    def _batches_trained(self) -> int:
        trainer = self.trainer
        return 0 if trainer is None else trainer.global_step * trainer.accumulate_grad_batches

    def _items(self, split: str) -> TorchDataLoader:
        dataset = self._splits[split]
        return TorchDataLoader(
            dataset, batch_size=None, sampler=EachOnceSampler(dataset), collate_fn=identity_collate
        )

    def val_dataloader(self) -> TorchDataLoader:
        """Whole validation trajectories."""
        return self._items("val")

    def test_dataloader(self) -> TorchDataLoader:
        """Whole test trajectories."""
        return self._items("test")

    def predict_dataloader(self) -> TorchDataLoader:
        """Process settings to roll out: single items, or lists of ``predict_batch_size``."""
        if self.hparams.predict_batch_size == 1:
            return self._items("predict")
        dataset = self._splits["predict"]
        return TorchDataLoader(
            dataset,
            batch_size=self.hparams.predict_batch_size,
            sampler=EachOnceSampler(dataset),
            collate_fn=list_collate,
        )

    # ---- used by the model -------------------------------------------------------------------
    def statistics_samples(self, count: int) -> list[HierarchicalData]:
        """``count`` training windows spread evenly over the training set (for normalisation statistics)."""
        assert self.train_dataset is not None, "call setup('fit') first"
        n = len(self.train_dataset)
        stride = max(1, math.ceil(n / max(count, 1)))
        return (self.train_dataset[i] for i in range(0, n, stride))  # type: ignore[return-value]

    def mesh_keys(self, split: str) -> dict[str, int]:
        """Topology keys (:func:`~torch_ampn.data.dataset.topology_key`) -> node counts of a split's meshes.

        Trajectory files are memory-mapped, only their cells read; ``"predict"`` gives the
        mesh of the dataset's simulator settings (``dataset.json``).
        """
        if split == "predict":
            items = self._splits.get("predict")
            if not items:
                return {}
            traj = items[0].trajectory
            return {topology_key(traj): traj.num_nodes}
        return dict(file_topology_key(f) for f in split_files(self.data_dir, split))

    def check_meshes(self, known: dict[str, int], split: str) -> None:
        """``ValueError`` naming the first file of ``split`` whose mesh is not among ``known``.

        ``known``: topology key -> node count of the meshes a model was trained on.
        """
        if not known:
            return
        if split == "predict":
            keys = self.mesh_keys("predict")
            source = self.hparams.get("predict_template") or self.data_dir / "dataset.json"
            unknown = [(source, n) for key, n in keys.items() if key not in known]
        else:
            found = (
                (path, *file_topology_key(path))
                for path in split_files(self.data_dir, split)[: self._split_size(split)]
            )
            unknown = [(path, n) for path, key, n in found if key not in known]
        if unknown:
            path, nodes = unknown[0]
            sizes = ", ".join(f"{n:,}" for n in sorted(set(known.values())))
            what = "its"
            if split == "predict" and not self.hparams.get("predict_template"):
                what = "the simulator settings make"
            raise ValueError(
                f"{path}: {what} mesh ({nodes:,} nodes) is not one the model was trained on "
                f"(meshes of {sizes} nodes); set model.check_mesh false to roll it out anyway"
            )

    def _split_size(self, split: str) -> int | None:
        items = self._splits.get(split)
        return len(items) if items is not None else None

    def _family_components(self) -> int:
        """Most components of any part of the dataset's family (``dataset.json``), 0 without one."""
        spec = self.data_dir / "dataset.json"
        if not spec.exists():
            return 0
        try:
            family = json.loads(spec.read_text()).get("family")
        except (ValueError, AttributeError):
            return 0
        return int(family["num_plies"][1]) + 2 if family else 0  # plies, punch and die

    def check_model(self, surrogate: torch.nn.Module) -> None:
        """Raise a clear error if the model's component/gripper counts or prior do not match the data."""
        bundle = getattr(surrogate, "bundle_steps", 1)
        if bundle != self.hparams.get("bundle_steps", 1):
            raise ValueError(
                f"model.bundle_steps={bundle} but data.bundle_steps={self.hparams.get('bundle_steps', 1)}: "
                "set both (the torch-ampn CLI links them)"
            )
        wants_prior = bool(getattr(surrogate, "prior_features", False))
        if wants_prior != (self.hparams.get("prior") is not None):
            raise ValueError(
                "the model reads a prior (model.prior_features, or a direct model's base: prior) and "
                "needs data.prior (e.g. pod_gp)"
                if wants_prior
                else f"data.prior is {self.hparams.prior!r} but the model reads no prior "
                "(set model.prior_features true, or a direct model's model.base: prior)"
            )
        split = next((s for s in ("train", "val", "test") if split_files(self.data_dir, s)), None)
        if split is None:
            return
        traj = Trajectory.load(split_files(self.data_dir, split)[0])
        if traj.num_grippers != surrogate.num_grippers:
            raise ValueError(
                f"model.num_grippers={surrogate.num_grippers} but the trajectories in {self.data_dir} "
                f"have {traj.num_grippers}"
            )
        components = max(traj.num_components, self._family_components())
        if getattr(surrogate, "component_encoding", "onehot") == "stack":  # up to C components
            if components > surrogate.num_components:
                raise ValueError(
                    f"model.num_components={surrogate.num_components} but the trajectories in "
                    f"{self.data_dir} have up to {components}; raise it to the most of any part"
                )
        elif components != surrogate.num_components:
            raise ValueError(
                f"model.num_components={surrogate.num_components} but the trajectories in {self.data_dir} "
                f"have {components}"
                + (
                    ""
                    if traj.meta.get("part") is None
                    else " (a family of parts: use model.component_encoding stack)"
                )
            )
        levels = self.hierarchies(traj).num_levels
        if levels < surrogate.num_levels:
            raise ValueError(
                f"the model uses num_levels={surrogate.num_levels} but the hierarchy of "
                f"{self.data_dir}'s mesh has "
                f"{levels} levels (data.min_coarse_nodes={self.hparams.min_coarse_nodes}); "
                "lower model.num_levels"
            )
