"""NextStepLightningModule: the seed paper's next-step residual training, rolled out autoregressively."""

from __future__ import annotations

from typing import Any

import torch

from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.training.inputs import add_training_noise, pushforward_inputs
from torch_ampn.training.module import NETWORK_ARGUMENTS, SurrogateLightningModule

#: The module's arguments that build its :class:`~torch_ampn.forming.AMPNSurrogate`.
SURROGATE_ARGUMENTS = (
    *NETWORK_ARGUMENTS,
    "diffusion_steps",
    "contact_positions",
    "center_target",
    "predict_change",
    "huber_delta",
    "coarse_loss_weight",
    "prior_features",
    "prior_base",
    "network_class",
    "network_options",
    "bundle_steps",
)


class NextStepLightningModule(SurrogateLightningModule):
    r"""Trains an :class:`~torch_ampn.forming.AMPNSurrogate` with the seed paper's recipe.

    * **fit**: MSE on the normalised next-step residual of ply nodes (ROBIN mode with
      ``diffusion_steps > 1``: the v-prediction loss at a random diffusion step); training
      noise ``position_noise`` * :math:`\sigma_x` on ply positions and ``residual_noise`` *
      :math:`\sigma_x` on the previous residual (:math:`\sigma_x`: std of training node
      positions); optionally pushforward batches. The schedule, statistics, validation, test
      and predict are :class:`~torch_ampn.training.SurrogateLightningModule`'s, whose
      arguments (the network's size, contact, learning rate, outputs) it takes too.
    * **validate, test, predict**: full autoregressive rollouts.

    Args:
        diffusion_steps: ROBIN's K (1 = AMPN).
        contact_positions: ``"current"`` (the paper: rebuilt every step) or ``"initial"`` (ROBIN).
        center_target: Standardise the target residual (``False``: only scale it).
        predict_change: Predict the change of the residual instead of the residual.
        huber_delta: Huber form of the loss beyond this normalised error (``None``: MSE).
        coarse_loss_weight: Weight of the multilevel loss's coarse terms (0: the paper's MSE).
        prior_features: Take a prior trajectory (the data module's ``prior``, e.g. POD + GP) as
            input and learn its correction (:func:`~torch_ampn.forming.features.prior_features`);
            rollouts then take the plain path.
        prior_base: With ``prior_features``: learn the departure of each step from the prior's
            step and add the prior's step back (see :class:`~torch_ampn.forming.AMPNSurrogate`);
            rollouts then take the plain path.
        network_class: Another network in place of the AMPN (``"package.module:Class"``, e.g. a
            peer's model behind an adapter; see :class:`~torch_ampn.forming.AMPNSurrogate`); the AMPN's
            layer arguments are then unused, and rollouts take the plain path.
        network_options: Keyword arguments of ``network_class``.
        bundle_steps: Temporal bundling: one call predicts the next ``B`` saved steps (see
            :class:`~torch_ampn.forming.AMPNSurrogate`); the data module's ``bundle_steps`` must
            match (the CLI links them). Not with ``pushforward``; rollouts take the plain path.
        position_noise: Training noise on ply positions, in units of :math:`\sigma_x` (paper: 1e-5).
        residual_noise: Training noise on the previous residual, in units of :math:`\sigma_x` (paper: 1e-6).
        correct_target: Subtract the position noise from the target residual, so that the model learns
            to pull a perturbed node back to the true next position (as MeshGraphNets do); only
            matters for noise levels well above the paper's.
        correlated_noise: Add the position noise to the previous residual too, as it is when
            :math:`x^{t-1}` comes from a rollout (the noise of MeshGraphNets, where velocities
            are differences of noisy positions). ``False`` (the paper): independent noise.
        pushforward: Probability that a training batch starts from the model's own one-step
            prediction of :math:`x^{t-1}` instead of the true one (the pushforward trick of
            Brandstetter et al., 2022), so that the model learns to correct the errors a rollout
            feeds it. Costs one forward pass per affected batch; 0 (the paper): off.
        rollout_seed: Seed of the noise input during rollouts (rollouts are reproducible).
        compile_network: Run the training step's network through ``torch.compile(dynamic=True)``
            (faster per step after a one-time compile at the first step; ``benchmarks/training_step.py``
            measures both). Validation, test and predict stay eager, and checkpoints are the
            same as without it. If compiling fails (e.g. no C++ compiler), training warns and
            goes on eager.
        fast_rollout: Roll out (validate, test, predict) on the static-shape, compiled path
            (:class:`~torch_ampn.rollout.fast.FastRollout`: the same result up to summation
            order, compiled once per mesh); ``False``: the plain path of
            :func:`~torch_ampn.rollout.rollout`. Contact settings without a fast path
            (``contact_mode="radius"``) take the plain path with a warning.
        **kwargs: :class:`~torch_ampn.training.SurrogateLightningModule`'s arguments.

    Example::

        module = NextStepLightningModule(hidden_channels=32, mlp_channels=32, num_levels=3)
    """

    MODEL = "next_step"

    def __init__(
        self,
        diffusion_steps: int = 1,
        contact_positions: str = "current",
        center_target: bool = True,
        predict_change: bool = False,
        huber_delta: float | None = None,
        coarse_loss_weight: float = 0.0,
        prior_features: bool = False,
        prior_base: bool = False,
        network_class: str | None = None,
        network_options: dict[str, Any] | None = None,
        bundle_steps: int = 1,
        position_noise: float = 1e-5,
        residual_noise: float = 1e-6,
        correct_target: bool = True,
        correlated_noise: bool = False,
        pushforward: float = 0.0,
        rollout_seed: int = 0,
        compile_network: bool = False,
        fast_rollout: bool = True,
        **kwargs: Any,
    ) -> None:
        if not 0.0 <= pushforward <= 1.0:
            raise ValueError(f"pushforward is a probability in [0, 1], got {pushforward}")
        if pushforward > 0 and bundle_steps > 1:
            raise ValueError("pushforward > 0 does not work with bundle_steps > 1: set pushforward: 0")
        self.check_arguments(kwargs)
        super().__init__(**kwargs)

    def build_surrogate(self) -> AMPNSurrogate:
        """The :class:`~torch_ampn.forming.AMPNSurrogate` of :data:`SURROGATE_ARGUMENTS`."""
        return AMPNSurrogate(**{name: self.hparams[name] for name in SURROGATE_ARGUMENTS})

    def _compile_loss(self) -> bool:
        return bool(self.hparams.compile_network)

    @property
    def _fast_rollout(self) -> bool:
        return bool(self.hparams.fast_rollout)

    def _generator(self, index: int) -> torch.Generator:
        return torch.Generator(device=self.device).manual_seed(self.hparams.rollout_seed + index)

    @property
    def _compiled_network(self):
        """The compiled network (``None``: not yet compiled; ``False``: eager), see :class:`CompiledLoss`."""
        return self._loss.network

    def add_training_noise(self, data: HierarchicalData) -> HierarchicalData:
        r"""The module's training noise (:func:`~torch_ampn.training.inputs.add_training_noise`), in place.

        ``position_noise`` and ``residual_noise`` are in units of the surrogate's :math:`\sigma_x`.
        """
        hp = self.hparams
        return add_training_noise(
            data, self.surrogate.position_std, hp.position_noise, hp.residual_noise,
            correct_target=hp.correct_target, correlated_noise=hp.correlated_noise,
        )  # fmt: skip

    def pushforward_inputs(self, data: HierarchicalData) -> HierarchicalData:
        """:func:`~torch_ampn.training.inputs.pushforward_inputs` with the surrogate's residual, in place."""
        return pushforward_inputs(data, self.surrogate.predict_residual)

    def training_inputs(self, batch: HierarchicalData) -> HierarchicalData:
        """The batch as the loss sees it, in place: pushed forward (probability ``pushforward``), noised."""
        if self.hparams.pushforward > 0 and float(torch.rand(())) < self.hparams.pushforward:
            batch = self.pushforward_inputs(batch)
        return self.add_training_noise(batch)
