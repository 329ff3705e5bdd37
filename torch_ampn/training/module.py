"""The Lightning module both forming surrogates share: set-up, statistics, schedule, rollouts and reports.

:class:`~torch_ampn.training.NextStepLightningModule` (the seed paper's next-step model) and
:class:`~torch_ampn.training.DirectLightningModule` (one pass per trajectory) subclass it, each
with the arguments of its own model.
"""

from __future__ import annotations

import inspect
import os
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from torch_ampn.forming.direct import DirectSurrogate
from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.rollout import rollout_rmse, rollout_surrogate
from torch_ampn.training.baseline_rollouts import BaselineRollouts
from torch_ampn.training.compiled_loss import CompiledLoss
from torch_ampn.training.free_cpu import FollowFreeCpu
from torch_ampn.training.items import RolloutItem, gather_objects
from torch_ampn.training.protocol import forecast_source
from torch_ampn.training.report import TestReport, write_prediction
from torch_ampn.training.rng import restore_rng_states, rng_states
from torch_ampn.training.schedule import WarmupExponentialDecay


def _check_writable(folder: Path, name: str) -> None:
    """Raise ``PermissionError`` naming ``folder`` and the setting unless files can be written there."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise PermissionError(f"{folder}: cannot write there ({name}): {err.strerror or err}") from None


#: The arguments of the network's size and shape, for both surrogates.
NETWORK_ARGUMENTS = (
    "num_components",
    "num_grippers",
    "hidden_channels",
    "mlp_channels",
    "num_levels",
    "pre_layers",
    "down_layers",
    "solve_layers",
    "post_layers",
    "up_layers",
    "aggr",
    "contact_radius",
    "contact_k",
    "contact_mode",
    "component_encoding",
)


def checkpoint_model(checkpoint: dict[str, Any]) -> str:
    """The model a loaded checkpoint holds: ``"next_step"`` or ``"direct"`` (or what it names).

    Read from ``checkpoint["torch_ampn_model"]``; in checkpoints written before that field
    (2026-12), from the hyper-parameter ``mode``.
    """
    if checkpoint.get("torch_ampn_model"):
        return str(checkpoint["torch_ampn_model"])
    return str((checkpoint.get("hyper_parameters") or {}).get("mode", "next_step"))


class SurrogateLightningModule(L.LightningModule):
    r"""What the forming surrogates' Lightning modules share (use a subclass).

    * **fit**: the surrogate's loss (the subclass's :meth:`training_inputs` prepare the batch);
      Adam; linear warm-up over ``warmup_steps`` then exponential decay ``lr -> final_lr`` over
      the remaining steps, stepped per optimiser step (with ``trainer.max_time`` set, the decay
      ends at ``final_lr`` when either the steps or the time run out, see
      :class:`~torch_ampn.training.schedule.WarmupExponentialDecay`). Gradient clipping at
      norm 1 is the Trainer's ``gradient_clip_val`` (the ``torch-ampn`` CLI sets it).
      Normalisation statistics come from up to ``statistics_samples`` training samples before
      the first step and are stored in the checkpoint.
    * **validate**: the prediction of each validation trajectory; logs ``val/rollout_rmse``
      (mm over ply nodes, averaged over steps).
    * **test**: the same on the test trajectories, side by side with the trivial and
      setting-aware baselines (:mod:`torch_ampn.baselines`); writes a CSV table, plots and
      XDMF rollouts to ``output_dir`` (see :class:`~torch_ampn.training.report.TestReport`).
    * **predict**: predictions of new process settings without ground truth (XDMF + PNG).

    The network's arguments are flat arguments of the module so that configs read
    ``model.init_args.num_levels``, the command line takes ``--model.num_levels 3``, the CLI
    links the contact settings into the data module, and checkpoints hold plain values.
    Checkpoints load with :meth:`load_from_checkpoint` (any subclass's, and those written
    before the split into two modules: :func:`~torch_ampn.training.load_module`).

    Args:
        num_components: Components of the mesh (plies + tools; 6 for the default dataset); with
            ``component_encoding: stack``, the most of any part of a family.
        num_grippers: Grippers (2 for the default dataset).
        hidden_channels: Latent size d (paper: 128).
        mlp_channels: Hidden width of every layer MLP (paper: 128, whatever d is).
        num_levels: V-cycle levels L + 1 (paper: 4; 1 = flat MeshGraphNet baseline).
        pre_layers: Pre stack layers (paper: 3).
        down_layers: Down stack layers (paper: 2).
        solve_layers: Solve stack layers (paper: 5).
        post_layers: Post stack layers (paper: 3).
        up_layers: Up stack layers (paper: 2).
        aggr: Aggregation of all layers (``"max"``, ``"sum"``, ``"mean"``).
        contact_radius: Contact radius r (mm).
        contact_k: Contact neighbours per other component.
        contact_mode: ``"component_knn"`` (the paper) or ``"radius"`` (all nodes within r).
        component_encoding: ``"onehot"`` (the paper's component one-hot, one part) or
            ``"stack"`` (plies below and above a ply node: the same on parts of any ply count;
            :func:`~torch_ampn.forming.features.component_features`).
        lr: Peak learning rate (paper: 1e-4).
        final_lr: Learning rate at the last step (paper: 1e-5).
        warmup_steps: Linear warm-up steps (paper: 1,000).
        statistics_samples: Training samples used for the normalisation statistics.
        touch_radii: Radii (mm) tried for the rigid-with-punch baseline; the best is reported.
        output_dir: Where test/predict write their files (default: the logger's folder, else ``outputs``).
        export_xdmf: Write XDMF rollouts in test and predict.
        check_mesh: Refuse to validate, test or predict (outside ``fit``) trajectories whose
            mesh is not one of the training split's (the checkpoint records them), with a
            message naming the file; ``False`` for a model meant for other parts.
    """

    #: The model's name in checkpoints (``checkpoint["torch_ampn_model"]``) and in ``data.mode``.
    MODEL: str = ""

    def __init__(
        self,
        num_components: int = 6,
        num_grippers: int = 2,
        hidden_channels: int = 128,
        mlp_channels: int = 128,
        num_levels: int = 4,
        pre_layers: int = 3,
        down_layers: int = 2,
        solve_layers: int = 5,
        post_layers: int = 3,
        up_layers: int = 2,
        aggr: str = "max",
        contact_radius: float = 3.0,
        contact_k: int = 3,
        contact_mode: str = "component_knn",
        component_encoding: str = "onehot",
        lr: float = 1e-4,
        final_lr: float = 1e-5,
        warmup_steps: int = 1000,
        statistics_samples: int = 1000,
        touch_radii: tuple[float, ...] = (3.0, 6.0, 9.0, 12.0),
        output_dir: str | None = None,
        export_xdmf: bool = True,
        check_mesh: bool = True,
    ) -> None:
        super().__init__()
        if not self.MODEL:
            raise TypeError(
                "SurrogateLightningModule is the shared base: "
                "use NextStepLightningModule or DirectLightningModule"
            )
        self.save_hyperparameters()
        self.surrogate = self.build_surrogate()
        self._report: TestReport | None = None
        # the loss, through the network compiled at the first training step (kept out of the module tree)
        self._loss = CompiledLoss(self.surrogate, enabled=self._compile_loss())
        # topology key -> node count of the training split's meshes (set by fit, kept in checkpoints)
        self._training_meshes: dict[str, int] | None = None
        # id of the Trainer whose fit _prepare_fit has done (configure_model and setup both ask)
        self._fit_prepared_for: int | None = None

    @classmethod
    def check_arguments(cls, kwargs: dict[str, Any]) -> None:
        """``TypeError`` in one line for arguments the shared base does not take (before ``__init__``).

        Names the other model's module where the argument is that model's.
        """
        shared = inspect.signature(SurrogateLightningModule.__init__).parameters
        for name in kwargs:
            if name in shared:
                continue
            owner = next(
                (k.__name__ for k in SurrogateLightningModule.__subclasses__()
                 if k is not cls and name in inspect.signature(k.__init__).parameters),
                None,
            )  # fmt: skip
            where = f"{name} is {owner}'s" if owner else f"no argument {name}"
            raise TypeError(f"{cls.__name__}: {where} (see help({cls.__name__}))")

    # ---- what a subclass decides -----------------------------------------------------------
    def build_surrogate(self) -> AMPNSurrogate | DirectSurrogate:
        """The surrogate of the module's hyper-parameters (the subclass's model)."""
        raise NotImplementedError

    def _compile_loss(self) -> bool:
        """Whether the training loss runs through the compiled network (see :class:`CompiledLoss`)."""
        return False

    def training_inputs(self, batch: HierarchicalData) -> HierarchicalData:
        """The batch as the loss sees it (here: as it is)."""
        return batch

    def _generator(self, index: int) -> torch.Generator | None:
        """The noise generator of rollout ``index`` (``None``: the model draws no noise)."""
        return None

    @property
    def _fast_rollout(self) -> bool:
        """Whether rollouts take the static-shape, compiled path where the surrogate allows it."""
        return True

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: str | os.PathLike,
        map_location: Any = None,
        strict: bool | None = None,
        **kwargs: Any,
    ) -> SurrogateLightningModule:
        """The module a checkpoint holds, as its own class (see :func:`~torch_ampn.training.load_module`).

        Called on a subclass, a checkpoint of the other model is refused in one line.
        ``kwargs`` override saved hyper-parameters (``weights_only`` is accepted and ignored:
        checkpoints always load weights-only; ``hparams_file`` is refused).
        """
        from torch_ampn.training.checkpoint import load_module

        kwargs.pop("weights_only", None)
        if kwargs.pop("hparams_file", None) is not None:
            raise TypeError(
                f"{cls.__name__}.load_from_checkpoint: hparams_file is not read; give overrides as keywords"
            )
        return load_module(checkpoint_path, map_location=map_location, strict=strict, expected=cls, **kwargs)

    # ---- set-up --------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        """Check the data and the output folders; before fitting, accumulate the normalisation statistics."""
        datamodule = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if self._trainer is not None:
            folders = [("model.output_dir", self.hparams.output_dir)]
            folders += [("checkpoint dirpath", getattr(c, "dirpath", None)) for c in self.trainer.callbacks]
            for name, folder in folders:
                if folder:
                    _check_writable(Path(folder), name)
        if stage == "fit":
            self._prepare_fit(datamodule)
        elif (source := forecast_source(datamodule)) is not None:
            source.check_model(self.surrogate)

    def configure_model(self) -> None:
        """Before a fit: :meth:`_prepare_fit` (the statistics, and a direct model's mean base).

        Weight-averaging callbacks copy the model in their own ``setup``, which runs before the
        module's and calls this hook first: so the copy holds the statistics too (a direct
        model's mean base is sized by the data). Outside ``fit`` it does nothing.
        """
        if self._trainer is not None and self.trainer.state.fn == "fit":
            self._prepare_fit(getattr(self.trainer, "datamodule", None))

    def teardown(self, stage: str) -> None:
        """After a fit: the next fit prepares again."""
        self._fit_prepared_for = None

    def _prepare_fit(self, datamodule: Any) -> None:
        """Once per fit: check the model against the data, note the meshes, fit the statistics.

        The statistics come from ``datamodule``'s training samples, unless frozen (a resumed fit).
        """
        trainer = None if self._trainer is None else id(self.trainer)
        if trainer is not None and trainer == self._fit_prepared_for:
            return
        source = forecast_source(datamodule)
        if source is not None:
            source.check_model(self.surrogate)
            self._training_meshes = source.mesh_keys("train")
        if not self.surrogate.statistics_frozen:
            if source is None:
                raise RuntimeError(
                    "fitting needs a data module with torch_ampn.training.ForecastDataSource's methods "
                    "(AMPNDataModule has them), for the normalisation statistics"
                )
            self.fit_statistics(source.statistics_samples(self.hparams.statistics_samples))
        self._fit_prepared_for = trainer

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Store the model's name and the generators' states (a resumed fit draws what it would have)."""
        checkpoint["torch_ampn_model"] = self.MODEL
        checkpoint["rng_states"] = rng_states()
        if self._training_meshes is not None:
            checkpoint["training_meshes"] = dict(self._training_meshes)

    def configure_callbacks(self) -> list:
        """The fit's callbacks: :class:`~torch_ampn.training.free_cpu.FollowFreeCpu`.

        The training steps' thread count follows the cores other processes leave free
        (``AMPN_THREADS=off``: torch's count).
        """
        return [FollowFreeCpu()]

    def on_train_start(self) -> None:
        """Restore the random generators' states of a resumed fit (see :meth:`on_load_checkpoint`)."""
        states = getattr(self, "_rng_states_to_restore", None) or {}
        object.__setattr__(self, "_rng_states_to_restore", None)
        restore_rng_states(states)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the generators' states for :meth:`on_train_start`; rebuild the surrogate of old checkpoints.

        Those checkpoints' layer MLPs were ``hidden_channels`` wide (the default then); Lightning
        calls this hook after building the module from the checkpoint's hyper-parameters and
        before loading its weights, so the surrogate is rebuilt with that width here.
        """
        saved_model = checkpoint_model(checkpoint)
        if saved_model != self.MODEL:
            raise ValueError(
                f"the checkpoint holds a {saved_model} model, not a {type(self).__name__}'s: "
                "load it with torch_ampn.training.load_module"
            )
        # applied when training starts: Lightning draws from the generator in between (a new
        # training-loader iterator takes a worker seed), which the stopped run had done before
        object.__setattr__(self, "_rng_states_to_restore", checkpoint.get("rng_states", {}))
        if checkpoint.get("training_meshes") is not None:  # older checkpoints: no mesh check
            self._training_meshes = {str(k): int(v) for k, v in checkpoint["training_meshes"].items()}
        saved = checkpoint.get("hyper_parameters", {})
        if "mlp_channels" in saved or self.hparams.mlp_channels == self.hparams.hidden_channels:
            return
        self.hparams.mlp_channels = self.hparams.hidden_channels
        device = next(self.surrogate.parameters()).device
        self.surrogate = self.build_surrogate().to(device)
        self._loss = CompiledLoss(self.surrogate, enabled=self._compile_loss())

    def fit_statistics(self, samples: Any) -> None:
        """Accumulate normalisation statistics from training windows (an iterable), then freeze them."""
        from tqdm.auto import tqdm

        enabled = self._trainer is None or self.trainer.is_global_zero
        for data in tqdm(samples, desc="normalisation statistics", unit="window", disable=not enabled):
            self.surrogate.accumulate_statistics(data)
        self.surrogate.freeze_statistics()

    def configure_optimizers(self) -> dict[str, Any]:
        """Adam with the warm-up + exponential-decay schedule, stepped per optimiser step."""
        hp = self.hparams
        optimizer = torch.optim.Adam(self.parameters(), lr=hp.lr)
        factor = WarmupExponentialDecay(
            hp.warmup_steps, self._total_steps(), hp.lr, hp.final_lr, time_remaining=self._time_remaining_fn()
        )
        # a plain function, not the callable object: LambdaLR would put the object's attributes
        # (the clock, the Timer's method) into checkpoints, which weights-only loading rejects
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: factor(step))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def _time_remaining_fn(self):
        """``Timer.time_remaining`` of the Trainer's ``max_time`` limit, or ``None`` without one."""
        if self._trainer is None:
            return None
        from lightning.pytorch.callbacks import Timer

        for callback in self.trainer.callbacks:
            if isinstance(callback, Timer) and callback.time_remaining() is not None:
                return callback.time_remaining
        return None

    def _total_steps(self) -> int:
        if self._trainer is None:
            return max(self.hparams.warmup_steps + 1, 1)
        total = self.trainer.estimated_stepping_batches
        if total is None or total == float("inf"):
            raise ValueError(
                "set trainer.max_steps (or max_epochs): the LR schedule needs the number of steps"
            )
        return int(total)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        """Training windows move as usual; rollout items move inside :func:`~torch_ampn.rollout.rollout`."""
        if isinstance(batch, RolloutItem):
            return batch
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    # ---- training --------------------------------------------------------------------------
    def training_loss(self, data: HierarchicalData) -> Tensor:
        """The surrogate's loss on a (noised) batch.

        With ``compile_network`` it runs through the compiled network (compiled at the first call,
        :class:`~torch_ampn.training.compiled_loss.CompiledLoss`).
        """
        return self._loss(data)

    def training_step(self, batch: HierarchicalData, batch_idx: int) -> Tensor:
        """One loss on a batch: of next-step windows (see :meth:`training_inputs`) or whole trajectories."""
        loss = self.training_loss(self.training_inputs(batch))
        self.log("train/loss", loss, prog_bar=True, batch_size=batch.num_graphs)
        return loss

    # ---- rollouts ----------------------------------------------------------------------------
    def rollout_item(self, item: RolloutItem, progress: bool = False) -> tuple[Tensor, float]:
        """Roll the surrogate out over ``item``'s trajectory: ``([T+1, N, 3] positions, seconds)``."""
        generator = self._generator(item.index)
        start = time.perf_counter()
        (pred,) = rollout_surrogate(
            self.surrogate, [item.trajectory], item.hierarchy, [generator],
            fast=self._fast_rollout, device=self.device, progress=progress,
        )  # fmt: skip
        return pred, time.perf_counter() - start

    def _check_meshes(self, split: str) -> None:
        """With ``check_mesh``: ``ValueError`` if a trajectory of ``split`` has a mesh not trained on."""
        source = forecast_source(getattr(self.trainer, "datamodule", None))
        if not (self.hparams.check_mesh and self._training_meshes):
            return
        if source is not None:
            source.check_meshes(self._training_meshes, split)

    def on_validation_epoch_start(self) -> None:
        """Start collecting the validation trajectories' RMSE (outside ``fit``: check their meshes first)."""
        if not self.trainer.training and self.trainer.state.fn != "fit":
            self._check_meshes("val")
        self._val_rmse: dict[str, float] = {}

    def validation_step(self, item: RolloutItem, batch_idx: int) -> Tensor:
        """Full rollout of one validation trajectory (its RMSE is logged at the epoch's end)."""
        pred, _ = self.rollout_item(item)
        rmse = rollout_rmse(pred, item.trajectory.pos, item.trajectory.ply_mask)[1:].mean()
        self._val_rmse[item.name] = float(rmse)
        return rmse

    def on_validation_epoch_end(self) -> None:
        """Log ``val/rollout_rmse``: the mean over every validation trajectory of every rank, each once."""
        merged: dict[str, float] = {}
        for part in gather_objects(self._val_rmse):
            merged.update(part)
        if merged:
            self.log("val/rollout_rmse", sum(merged.values()) / len(merged), prog_bar=True, batch_size=1)

    def on_test_epoch_start(self) -> None:
        """Check the test trajectories' meshes; fit the setting-aware baselines; start a new test report."""
        self._check_meshes("test")
        self._report = TestReport(self.output_dir())
        datamodule = getattr(self.trainer, "datamodule", None)
        self._baselines, reason = BaselineRollouts.fitted(datamodule, self.hparams.touch_radii)
        if reason is not None and self.trainer.is_global_zero:
            print(f"setting-aware baselines: not reported ({reason})")

    def test_step(self, item: RolloutItem, batch_idx: int) -> Tensor:
        """Rollout of one test trajectory next to the baselines; rows go to the report."""
        traj = item.trajectory
        pred, seconds = self.rollout_item(item)
        rmse = rollout_rmse(pred, traj.pos, traj.ply_mask)  # [T+1]
        baselines = self._baselines.rmse(item)
        assert self._report is not None
        self._report.add(item, pred, rmse, baselines, seconds, xdmf=self.hparams.export_xdmf)
        return rmse[1:].mean()

    def on_test_epoch_end(self) -> None:
        """Write the table, plots and summary (rank 0, with every rank's trajectories); log the comparison."""
        assert self._report is not None
        parts = gather_objects((self._report.rows, self._report.curves))
        if self.trainer.is_global_zero:
            for name, why in self._baselines.refused.items():  # on this rank's trajectories
                print(f"setting-aware baseline {name}: left out of the comparison ({why})")
            self._report.merge(parts)
            summary = self._report.finish()
            numbers = {f"test/{k}": float(v) for k, v in summary.items() if isinstance(v, (int, float))}
            self.log_dict(numbers, rank_zero_only=True)

    def on_predict_epoch_start(self) -> None:
        """Check that the process settings' mesh is one the model was trained on."""
        self._check_meshes("predict")

    def predict_step(self, item: RolloutItem | list[RolloutItem], batch_idx: int) -> Tensor | list[Tensor]:
        """Rollout of new process settings: writes XDMF and a PNG each; returns positions ``[T+1, N, 3]``.

        A list of items (``data.predict_batch_size > 1``) is rolled out as one batch on the fast
        path where the items share a mesh; the seconds written per setting are the batch's share.
        """
        items = item if isinstance(item, list) else [item]
        results = self.rollout_items(items)
        for one, (pred, seconds) in zip(items, results, strict=True):
            write_prediction(self.output_dir() / "predict", one, pred, seconds, xdmf=self.hparams.export_xdmf)
        return [pred for pred, _ in results] if isinstance(item, list) else results[0][0]

    def rollout_items(self, items: list[RolloutItem]) -> list[tuple[Tensor, float]]:
        """:meth:`rollout_item` of several items, as one batch where the fast path allows it."""
        if len(items) == 1 or any(it.hierarchy is not items[0].hierarchy for it in items):
            return [self.rollout_item(it) for it in items]
        # one compiled batch size: the largest seen (a smaller last batch is padded)
        self._rollout_batch_size = max(getattr(self, "_rollout_batch_size", 1), len(items))
        start = time.perf_counter()
        preds = rollout_surrogate(
            self.surrogate, [it.trajectory for it in items], items[0].hierarchy,
            [self._generator(it.index) for it in items], fast=self._fast_rollout,
            batch_size=self._rollout_batch_size, device=self.device,
        )  # fmt: skip
        share = (time.perf_counter() - start) / len(items)
        return [(pred, share) for pred in preds]

    def output_dir(self) -> Path:
        """Folder for test and predict outputs."""
        if self.hparams.output_dir:
            return Path(self.hparams.output_dir)
        if self._trainer is not None and self.trainer.log_dir is not None:
            return Path(self.trainer.log_dir)
        return Path("outputs")
