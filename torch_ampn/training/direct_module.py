"""DirectLightningModule: (initial state, settings) -> every saved step's displacement, in one pass."""

from __future__ import annotations

from typing import Any

from torch_ampn.forming.direct import DirectSurrogate
from torch_ampn.training.module import NETWORK_ARGUMENTS, SurrogateLightningModule

#: The module's arguments that build its :class:`~torch_ampn.forming.direct.DirectSurrogate`.
DIRECT_ARGUMENTS = (
    *NETWORK_ARGUMENTS,
    "base",
    "time_frequencies",
    "decoder_layers",
    "loss_steps",
    "settings_input",
    "position_frequencies",
    "decoder_modes",
    "mode_channels",
    "mode_layers",
    "space_time_modes",
    "base_input",
    "target_scale",
)


class DirectLightningModule(SurrogateLightningModule):
    r"""Trains a :class:`~torch_ampn.forming.direct.DirectSurrogate` on whole trajectories.

    The model maps the initial state and the process settings to the displacement at every
    saved step in one pass: no rollout, no training noise (the data module's ``mode: direct``,
    which the ``torch-ampn`` CLI links, gives it whole trajectories). The schedule, statistics,
    validation, test and predict are :class:`~torch_ampn.training.SurrogateLightningModule`'s,
    whose arguments (the network's size, contact, learning rate, outputs) it takes too.

    Args:
        base: Predict the departure from the mean training displacement (``"mean"``, one mesh),
            the displacement itself (``"initial"``) or the departure from the data module's
            ``prior`` (``"prior"``, e.g. POD + GP's prediction; set ``data.prior``).
        time_frequencies: Frequencies of the time encoding.
        decoder_layers: Linear maps of the time decoder.
        loss_steps: Random saved steps per batch in the loss (``None``: all).
        settings_input: The grippers' positions and forces at t = 0 as a global input of every
            fine node and of the decoder.
        position_frequencies: Fourier features of the initial position read by the decoder
            (frequencies per axis; 0: none).
        decoder_modes: Learned modes with coefficients of the settings and time, added to the
            time decoder (:class:`~torch_ampn.forming.direct.ModeDecoder`; 0: none).
        mode_channels: Width of the modes' coefficient MLP (``None``: ``mlp_channels``).
        mode_layers: Linear maps of the coefficient MLP.
        space_time_modes: Modes of the node and the time, coefficients of the settings alone
            (POD + GP's form).
        base_input: With ``base: mean``: the nodes read the mean training displacement at this
            many evenly spaced steps and the decoder at the asked time (0: neither).
        target_scale: The scale of the network's output, ``"global"``, or with ``base: mean`` the
            training spread at each step (``"step"``) or node and step (``"node_step"``).
        **kwargs: :class:`~torch_ampn.training.SurrogateLightningModule`'s arguments.

    Example::

        module = DirectLightningModule(hidden_channels=64, mlp_channels=64, num_levels=3, decoder_modes=32)
    """

    MODEL = "direct"

    def __init__(
        self,
        base: str = "mean",
        time_frequencies: int = 5,
        decoder_layers: int = 3,
        loss_steps: int | None = None,
        settings_input: bool = True,
        position_frequencies: int = 4,
        decoder_modes: int = 0,
        mode_channels: int | None = None,
        mode_layers: int = 3,
        space_time_modes: bool = False,
        base_input: int = 0,
        target_scale: str = "global",
        **kwargs: Any,
    ) -> None:
        self.check_arguments(kwargs)
        super().__init__(**kwargs)

    def build_surrogate(self) -> DirectSurrogate:
        """The :class:`~torch_ampn.forming.direct.DirectSurrogate` of :data:`DIRECT_ARGUMENTS`."""
        return DirectSurrogate(**{name: self.hparams[name] for name in DIRECT_ARGUMENTS})
