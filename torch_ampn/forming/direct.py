r"""DirectSurrogate: (initial mesh, process settings) -> the displacement at every saved step, at once.

A next-step surrogate rolls out 50 steps and its error compounds; a regression of whole
trajectories on the settings (POD + GP) has no rollout. The direct surrogate is the second kind
on the mesh: one V-cycle of the AMPN over the initial state (the paper's node features at
:math:`t = 0`, with the gripper features of the process settings, and the contact edges of the
initial state) gives every node a latent code :math:`\mathbf{h}_i`, and a small decoder maps
:math:`(\mathbf{h}_i, \gamma(t))` to the node's displacement at time :math:`t` (a Fourier
encoding of the normalised time). So one network pass predicts every saved step, a design
study needs one pass per setting, and every prediction has the whole part's reach.

The displacement is predicted as a departure from a base: the mean training displacement of
every node and step (``base="mean"``, one mesh; the network learns the settings' effect), the
initial state (``base="initial"``, any mesh) or a prior's prediction of the trajectory
(``base="prior"``, e.g. POD + GP's; the network learns what the prior misses).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from torch_ampn.forming.features import (
    ampn_channels,
    hierarchical_features,
    num_coarse_node_features,
    num_edge_features,
)
from torch_ampn.forming.model_file import ModelFile
from torch_ampn.forming.normalizer import Normalizer
from torch_ampn.hierarchy.hierarchical_data import RELATIONS, HierarchicalData, level_name
from torch_ampn.nn.diffusion import RobinAMPN

BASES = ("mean", "initial", "prior")
TARGET_SCALES = ("global", "step", "node_step")


class TimeEncoding(nn.Module):
    r"""Fourier features of a normalised time :math:`t \in [0, 1]`.

    :math:`\gamma(t) = [t, \sin(\pi 2^k t), \cos(\pi 2^k t)]_{k < F}`: the lowest frequency is
    half a period over the process, the highest tells apart :math:`2^{F-1}` stretches of it.

    Shapes:
        - **input:** :math:`(*)`
        - **output:** :math:`(*, 2F + 1)`
    """

    frequencies: Tensor

    def __init__(self, num_frequencies: int = 5) -> None:
        super().__init__()
        if num_frequencies < 1:
            raise ValueError(f"time_frequencies must be >= 1, got {num_frequencies}")
        k = torch.arange(num_frequencies, dtype=torch.float32)
        self.register_buffer("frequencies", math.pi * torch.pow(2.0, k), persistent=False)

    @property
    def out_channels(self) -> int:
        """``2 F + 1``."""
        return 2 * self.frequencies.numel() + 1

    def forward(self, t: Tensor) -> Tensor:
        """``[*] -> [*, 2F + 1]``."""
        angle = t.float().unsqueeze(-1) * self.frequencies  # [*, F]
        return torch.cat([t.float().unsqueeze(-1), angle.sin(), angle.cos()], dim=-1)


class TimeDecoder(nn.Module):
    r"""The displacement of every node at every asked time from its latent code: ``[N, d], [S] -> [N, S, 3]``.

    :math:`\mathrm{MLP}(\mathrm{LayerNorm}(\mathbf{h}_i) \oplus \gamma(t))` with SiLU and
    ``layers`` linear maps; the first is split into a node part and a time part, so that the
    ``[N, S, d + 2F + 1]`` concatenation is never built.

    Args:
        latent_channels: ``d``.
        hidden_channels: Width of the hidden layers.
        out_channels: Output per node and time (3: a displacement).
        time_frequencies: ``F`` of :class:`TimeEncoding`.
        layers: Linear maps (at least 2).
        cond_channels: Columns of a per-node condition read with the latent code (e.g. the settings).
        normalize: Layer-normalise the latent code first.
        point_channels: Columns of a per-node, per-time input (e.g. the mean displacement at that time).
    """

    def __init__(
        self,
        latent_channels: int,
        hidden_channels: int = 128,
        out_channels: int = 3,
        time_frequencies: int = 5,
        layers: int = 3,
        cond_channels: int = 0,
        normalize: bool = True,
        point_channels: int = 0,
    ) -> None:
        super().__init__()
        if layers < 2:
            raise ValueError(f"decoder_layers must be >= 2, got {layers}")
        self.time = TimeEncoding(time_frequencies)
        self.norm = nn.LayerNorm(latent_channels) if normalize else nn.Identity()
        self.lin_node = nn.Linear(latent_channels + cond_channels, hidden_channels)
        self.lin_time = nn.Linear(self.time.out_channels, hidden_channels, bias=False)
        self.lin_point = nn.Linear(point_channels, hidden_channels, bias=False) if point_channels else None
        rest: list[nn.Module] = []
        for _ in range(layers - 2):
            rest += [nn.SiLU(), nn.Linear(hidden_channels, hidden_channels)]
        self.rest = nn.Sequential(*rest, nn.SiLU(), nn.Linear(hidden_channels, out_channels))

    def forward(
        self, h: Tensor, t: Tensor, cond: Tensor | None = None, point: Tensor | None = None
    ) -> Tensor:
        """``h [N, d]``, ``t [S]`` (normalised), ``cond [N, c]``, ``point [N, S, p]`` -> ``[N, S, out]``."""
        h = self.norm(h)
        node = self.lin_node(h if cond is None else torch.cat([h, cond.to(h.dtype)], dim=-1))  # [N, m]
        time = self.lin_time(self.time(t.to(h.device)))  # [S, m]
        first = node[:, None, :] + time[None, :, :]  # [N, S, m]
        if self.lin_point is not None:
            if point is None:
                raise ValueError("this decoder reads a per-node, per-time input (point); none was given")
            first = first + self.lin_point(point.to(h.dtype))
        return self.rest(first)  # [N, S, out]


class ModeDecoder(nn.Module):
    r"""``K`` learned modes with coefficients of the settings and time: ``[N, d], [B, c], [S] -> [N, S, 3]``.

    :math:`\mathbf{u}_i(t) = \sum_k b_k(\mathbf{s}, \gamma(t))\, \boldsymbol{\phi}_{ik}`: the trunk
    :math:`\boldsymbol{\phi}_{ik} \in \mathbb{R}^3` is a linear map of node :math:`i`'s (normalised)
    latent code, the branch :math:`b_k` an MLP of its sample's settings :math:`\mathbf{s}` and the
    time, as in a DeepONet. POD + GP has this form with fixed modes; here the modes are learned
    with the rest and the product lets a global setting scale a local shape directly.

    With ``space_time=True`` the time moves from the coefficients to the modes, POD + GP's exact
    form (a mode is the shape of a whole trajectory):
    :math:`\mathbf{u}_i(t) = \sum_k b_k(\mathbf{s})\, \boldsymbol{\phi}_k(\mathbf{h}_i, \gamma(t))`,
    the trunk a :class:`TimeDecoder` of the latent code, the branch an MLP of the settings alone.

    Args:
        latent_channels: ``d``.
        settings_channels: ``c`` (0: the coefficients depend on time alone).
        modes: ``K``.
        hidden_channels: Width of the branch MLP (SiLU).
        time_frequencies: ``F`` of :class:`TimeEncoding`.
        layers: Linear maps of the branch MLP (at least 2).
        space_time: Modes of the node and the time, coefficients of the settings alone.
    """

    def __init__(
        self,
        latent_channels: int,
        settings_channels: int,
        modes: int,
        hidden_channels: int = 128,
        time_frequencies: int = 5,
        layers: int = 3,
        space_time: bool = False,
    ) -> None:
        super().__init__()
        if modes < 1:
            raise ValueError(f"decoder_modes must be >= 1, got {modes}")
        if layers < 2:
            raise ValueError(f"mode_layers must be >= 2, got {layers}")
        self.modes = modes
        self.space_time = space_time
        # the space-time trunk normalises the latent code itself
        self.norm = nn.Identity() if space_time else nn.LayerNorm(latent_channels)
        self.trunk: nn.Module
        self.branch: nn.Module
        if space_time:
            # the modes: a time decoder of the latent code, [N, d], [S] -> [N, S, 3 K]
            self.trunk = TimeDecoder(latent_channels, hidden_channels, 3 * modes, time_frequencies, 3)
            # the coefficients: an MLP of the settings, [B, c] -> [B, K]
            sizes = [max(settings_channels, 1)] + [hidden_channels] * (layers - 1)
            hidden = [m for a, b in zip(sizes, sizes[1:], strict=False) for m in (nn.Linear(a, b), nn.SiLU())]
            self.branch = nn.Sequential(*hidden, nn.Linear(sizes[-1], modes))
            last = self.branch[-1]
        else:
            self.trunk = nn.Linear(latent_channels, 3 * modes)
            # the coefficients: a time decoder of the settings, [B, c], [S] -> [B, S, K]
            self.branch = TimeDecoder(
                max(settings_channels, 1), hidden_channels, modes, time_frequencies, layers, normalize=False
            )
            last = self.branch.rest[-1]
        # the modes start at zero: added to another decoder, this one first changes nothing
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    #: Parameter names of files written before the coefficients' MLP was a TimeDecoder (2026-12-05).
    OLD_NAMES = {
        "branch_settings.": "branch.lin_node.",
        "branch_time.": "branch.lin_time.",
        "branch.1.": "branch.rest.1.",
        "branch.3.": "branch.rest.3.",
    }

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # noqa: ANN001
        """Rename the parameters of older files (:attr:`OLD_NAMES`) before loading them."""
        for key in [k for k in state_dict if k.startswith(prefix)]:
            for old, new in self.OLD_NAMES.items():
                if key.startswith(prefix + old):
                    state_dict[prefix + new + key[len(prefix + old) :]] = state_dict.pop(key)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, h: Tensor, settings: Tensor, t: Tensor, batch: Tensor | None = None) -> Tensor:
        """``h [N, d]``, ``settings [B, c]``, ``t [S]``, ``batch [N]`` (or ``None``) -> ``[N, S, 3]``."""
        if self.space_time:
            phi = self.trunk(h, t).unflatten(-1, (self.modes, 3))  # [N, S, K, 3]
            coef = self.branch(settings.to(h.dtype))  # [B, K]
            coef = coef[batch] if batch is not None else coef.expand(h.size(0), -1)  # [N, K]
            return torch.einsum("nk,nskc->nsc", coef, phi)
        phi = self.trunk(self.norm(h)).unflatten(-1, (self.modes, 3))  # [N, K, 3]
        coef = self.branch(settings.to(h.dtype), t)  # [B, S, K]
        coef = coef[batch] if batch is not None else coef.expand(h.size(0), -1, -1)  # [N, S, K]
        return torch.einsum("nsk,nkc->nsc", coef, phi)


class DirectSurrogate(ModelFile, nn.Module):
    r"""Predictor of a whole forming trajectory from the initial state and the process settings.

    Inputs are windows at :math:`t = 1` (:func:`~torch_ampn.data.direct_sample`: the initial
    positions, zero previous motion, the tools' first step, the grippers' positions and forces)
    with contact edges of the initial state; a batch is a PyG ``Batch`` of them. Training
    targets are ``data["l0"].displacement`` ``[N, T, 3]``: :math:`x^t - x^0` of every saved step.

    Args:
        num_components: Components of the mesh (see :class:`~torch_ampn.forming.AMPNSurrogate`).
        num_grippers: Grippers.
        num_levels: V-cycle levels (1: a flat network).
        contact_radius: Contact radius of the initial state's contact edges (mm).
        contact_k: Contact neighbours per other component.
        contact_mode: See :class:`~torch_ampn.transforms.ComponentRadiusGraph`.
        gripper_alpha: Distance decay of the gripper features.
        component_encoding: ``"onehot"`` or ``"stack"`` (see :func:`~torch_ampn.forming.component_features`).
        base: ``"mean"``: the output is added to the mean training displacement of every node and
            step (one mesh, one step count); ``"initial"``: the output is the displacement;
            ``"prior"``: the output is added to the displacement of the sample's prior trajectory
            (``l0.prior_displacement`` of :func:`~torch_ampn.data.direct_sample`: the data
            module's ``prior``, out of fold on the training split; :attr:`prior_features` is then
            true, so that the data module, ``test`` and ``design`` supply it).
        time_frequencies: ``F`` of the time encoding.
        decoder_layers: Linear maps of the time decoder.
        loss_steps: Saved steps per trajectory in the training loss, drawn at random per batch
            (``None``: all; fewer save memory on large meshes).
        settings_input: Give every fine node and the decoder the grippers' positions and forces
            at :math:`t = 0` (``6 G`` numbers, normalised) besides the paper's distance-decayed
            gripper features: a global code of the process settings.
        position_frequencies: Fourier features of the initial position read by the decoder
            (frequencies per axis; 0: none).
        decoder_modes: Modes of a :class:`ModeDecoder` whose output is added to the time
            decoder's (0: none).
        mode_channels: Width of the modes' coefficient MLP (``None``: ``mlp_channels``); it runs
            once per sample and time, not per node, so width costs little.
        mode_layers: Linear maps of the coefficient MLP.
        space_time_modes: The modes are functions of the node and the time, their coefficients
            of the settings alone (POD + GP's form; see :class:`ModeDecoder`).
        target_scale: The scale of the departure from the base that the network's output is in:
            ``"global"``, one per axis; with ``base="mean"`` also ``"step"``, the training spread
            about the mean at each saved step and axis, so that the early steps, where the
            settings have moved the plies little yet, are fitted as closely as the late ones; or
            ``"node_step"``, each node's, step's and axis' spread (floored at 1 % of the global
            one): the settings' effect is then learned where the training data show one.
        base_input: With ``base="mean"``: every fine node reads the mean training displacement
            at this many evenly spaced saved steps (the last among them), and the time decoder
            reads it at the asked time; where the mean part ends up (the tools' imprint on it)
            is then an input, not something to learn (0: neither).
        **network: Further arguments of :class:`~torch_ampn.nn.RobinAMPN` (``hidden_channels``,
            ``mlp_channels``, the stacks' layer counts, ``aggr``); its output is the latent code,
            ``hidden_channels`` wide.
    """

    def __init__(
        self,
        num_components: int = 6,
        num_grippers: int = 2,
        num_levels: int = 4,
        contact_radius: float = 3.0,
        contact_k: int = 3,
        contact_mode: str = "component_knn",
        gripper_alpha: float = 3e-2,
        component_encoding: str = "onehot",
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
        **network: Any,
    ) -> None:
        super().__init__()
        arguments = {k: v for k, v in locals().items() if k not in ("self", "__class__", "network")}
        self.arguments: dict[str, Any] = {**arguments, **network}
        self.meta: dict[str, Any] = {}
        if base not in BASES:
            raise ValueError(f"base must be one of {BASES}, got {base!r}")
        if loss_steps is not None and loss_steps < 1:
            raise ValueError(f"loss_steps must be >= 1 or None, got {loss_steps}")
        if base_input < 0 or (base_input and base != "mean"):
            raise ValueError(
                f"base_input must be 0, or >= 1 with base='mean'; got {base_input} with {base!r}"
            )
        if target_scale not in TARGET_SCALES or (target_scale != "global" and base != "mean"):
            raise ValueError(
                f"target_scale must be one of {TARGET_SCALES} ('step' and 'node_step' with base='mean'); "
                f"got {target_scale!r} with {base!r}"
            )
        from torch_ampn.transforms.contact import ComponentRadiusGraph

        self.num_components = num_components
        self.num_grippers = num_grippers
        self.num_levels = num_levels
        self.gripper_alpha = gripper_alpha
        self.component_encoding = component_encoding
        #: Whether the samples must carry a prior trajectory (``base="prior"``).
        self.prior_features = base == "prior"
        self.base = base
        self.target_scale = target_scale
        self.loss_steps = loss_steps
        self.contact = ComponentRadiusGraph(
            r=contact_radius,
            k=contact_k,
            num_components=num_components,
            mode=contact_mode,
            positions="initial",
        )
        sizes = ampn_channels(num_components, num_grippers, component_encoding=component_encoding)
        latent = int(network.get("hidden_channels", 128))
        self.settings_input = bool(settings_input)
        code = 6 * num_grippers if self.settings_input else 0  # grippers' positions and forces at t = 0
        sizes["fine_in_channels"] += code
        raw_fine = sizes["fine_in_channels"]  # what node_norm["fine"] normalises
        self.base_input = int(base_input)
        sizes["fine_in_channels"] += 3 * self.base_input  # the mean displacement at base_input steps
        self.model = RobinAMPN(**sizes, out_channels=latent, num_levels=num_levels, **network)
        self.settings_norm = Normalizer(max(code, 1))
        self.position_frequencies = int(position_frequencies)
        self.position_norm = Normalizer(3)  # of the initial positions: what the Fourier features read
        cond = code + 6 * self.position_frequencies
        self.decoder = TimeDecoder(
            latent, int(network.get("mlp_channels", 128)), 3, time_frequencies, decoder_layers, cond,
            point_channels=3 if self.base_input else 0,
        )  # fmt: skip
        self.modes = (
            ModeDecoder(
                latent,
                code,
                decoder_modes,
                int(mode_channels or network.get("mlp_channels", 128)),
                time_frequencies,
                mode_layers,
                space_time_modes,
            )
            if decoder_modes
            else None
        )
        self.node_norm = nn.ModuleDict(
            {"fine": Normalizer(raw_fine), "coarse": Normalizer(num_coarse_node_features())}
        )
        self.edge_norm = nn.ModuleDict({rel: Normalizer(num_edge_features(rel)) for rel in RELATIONS})
        self.target_norm = Normalizer(3, center=False)  # the scale of the departure from the base
        # base="mean": the mean training displacement, one entry per (step, node, axis); sized by the data
        self.base_norm: Normalizer | None = None
        # (T, N) of the mean base once known: extra state, not a buffer (weight averaging would average it)
        self.base_shape: tuple[int, int] = (0, 0)
        # base_input: the scales of the mean base as the nodes ([N, 3 k]) and the decoder ([N, S, 3]) read it
        self.base_input_norm = Normalizer(3 * self.base_input) if self.base_input else None
        self.base_point_norm = Normalizer(3) if self.base_input else None

    # ---- statistics --------------------------------------------------------------------
    def _normalizers(self) -> list[Normalizer]:
        base = [] if self.base_norm is None else [self.base_norm]
        if self.base_input_norm is not None and self.base_point_norm is not None:
            base += [self.base_input_norm, self.base_point_norm]
        return [
            *self.node_norm.values(),
            *self.edge_norm.values(),
            self.target_norm,
            self.settings_norm,
            self.position_norm,
            *base,
        ]

    @property
    def statistics_frozen(self) -> bool:
        """Whether the normalisation statistics (and the mean base) are final."""
        if self.base == "mean" and self.base_norm is None:
            return False
        return all(bool(n.frozen) for n in self._normalizers())

    @torch.no_grad()
    def accumulate_statistics(self, data: HierarchicalData) -> None:
        """Add one training sample (not a batch) to the statistics and, with ``base="mean"``, the mean."""
        if "batch" in data["l0"]:
            raise ValueError("DirectSurrogate.accumulate_statistics takes single samples, not a batch")
        x_dict, e_dict = self._raw_features(data)
        self.position_norm.update(data["l0"].pos0)
        if self.settings_input:
            self.settings_norm.update(self._settings(data))
        for lk, x in x_dict.items():
            self.node_norm["fine" if lk == "l0" else "coarse"].update(x)
        for (_, rel, _), e in e_dict.items():
            self.edge_norm[rel].update(e)
        fine = data["l0"]
        disp = fine.displacement.transpose(0, 1)  # [T, N, 3]
        if self.base == "prior":
            disp = disp - self._prior(data).transpose(0, 1)  # the departure from the prior
        if self.base in ("initial", "prior"):
            self.target_norm.update(disp[:, fine.ply_mask])
            return
        if self.base_norm is None:
            self.base_norm = Normalizer(disp.numel()).to(disp.device)
            self.base_shape = (disp.size(0), disp.size(1))
        elif tuple(disp.shape[:2]) != self.base_shape:
            raise ValueError(
                f"base='mean' needs one mesh and step count: a sample has {disp.size(1)} nodes and "
                f"{disp.size(0)} steps, the first {self.base_shape[1]} and {self.base_shape[0]} "
                "(use base='initial' for a family of parts)"
            )
        self.base_norm.update(disp.reshape(1, -1))
        self._ply_mask = fine.ply_mask

    def freeze_statistics(self) -> None:
        """Freeze every normaliser (``base="mean"``: the departure's scale is the spread about the base)."""
        if self.base == "mean":
            if self.base_norm is None:
                raise RuntimeError("no training sample was seen: the mean base is unknown")
            steps, nodes = self.base_shape
            m2 = self.base_norm.running_m2.reshape(steps, nodes, 3)[:, self._ply_mask]  # [T, N_ply, 3]
            self.target_norm.count.fill_(float(self.base_norm.count) * m2.shape[0] * m2.shape[1])
            self.target_norm.running_m2.copy_(m2.sum((0, 1)))
            if self.base_input_norm is not None and self.base_point_norm is not None:
                mean = self.base_norm.running_mean.reshape(steps, nodes, 3)  # [T, N, 3]
                picked = mean[self._base_input_steps() - 1].transpose(0, 1).flatten(1)  # [N, 3 k]
                self.base_input_norm.update(picked)
                self.base_point_norm.update(mean.reshape(-1, 3))
        for n in self._normalizers():
            n.freeze()

    def get_extra_state(self) -> dict[str, list[int]]:
        """The mean base's shape ``(T, N)``, saved in the state dict."""
        return {"base_shape": list(self.base_shape)}

    def set_extra_state(self, state: dict[str, list[int]]) -> None:
        """Restore :meth:`get_extra_state`."""
        steps, nodes = state["base_shape"]
        self.base_shape = (int(steps), int(nodes))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # noqa: ANN001
        """Build the mean base's normaliser at the saved size before its buffers are loaded."""
        key = prefix + "base_norm.running_mean"
        if key in state_dict and (
            self.base_norm is None or self.base_norm.num_features != state_dict[key].numel()
        ):
            self.base_norm = Normalizer(state_dict[key].numel()).to(state_dict[key].device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _base_input_steps(self) -> Tensor:
        """The ``base_input`` saved steps (1-based) the nodes read the mean base at, ``LongTensor[k]``."""
        steps = self.base_shape[0]
        return torch.linspace(steps / self.base_input, steps, self.base_input).round().long().clamp(1, steps)

    # ---- features and prediction -------------------------------------------------------
    def _raw_features(self, data: HierarchicalData):
        """The paper's features of the used levels, the fine nodes' with the settings (``settings_input``)."""
        if data.num_levels < self.num_levels:
            raise ValueError(
                f"the model uses {self.num_levels} levels but the hierarchy has only {data.num_levels}; "
                "build a deeper hierarchy (smaller min_coarse_nodes) or lower num_levels"
            )
        x_dict, e_dict = hierarchical_features(
            data, self.num_components, self.num_levels, alpha=self.gripper_alpha,
            component_encoding=self.component_encoding,
        )  # fmt: skip
        if self.settings_input:
            x_dict["l0"] = torch.cat([x_dict["l0"], self._settings(data, per_node=True)], dim=-1)
        return x_dict, e_dict

    @staticmethod
    def _settings(data: HierarchicalData, per_node: bool = False) -> Tensor:
        """The grippers' positions and forces at :math:`t = 0`, ``[B, 6G]`` (``per_node``: ``[N_0, 6G]``)."""
        code = torch.cat([data.gripper_pos, data.gripper_force], dim=-1).flatten(1).float()  # [B, 6G]
        if not per_node:
            return code
        fine = data["l0"]
        batch = (
            fine.batch
            if "batch" in fine
            else torch.zeros(fine.num_nodes, dtype=torch.long, device=code.device)
        )
        return code[batch]

    def _condition(self, data: HierarchicalData) -> Tensor | None:
        r"""What the decoder reads besides the latent code, ``[N_0, c]`` (``None``: nothing).

        The normalised settings (``settings_input``) and Fourier features of the normalised
        initial position, :math:`\sin(2^k \hat x), \cos(2^k \hat x)`, ``k < position_frequencies``
        per axis: a displacement field's shape over the part is then quick to learn.
        """
        parts = []
        if self.settings_input:
            parts.append(self.settings_norm(self._settings(data, per_node=True)))
        if self.position_frequencies > 0:
            x = self.position_norm(data["l0"].pos0.float())  # [N_0, 3]
            scale = torch.pow(2.0, torch.arange(self.position_frequencies, device=x.device, dtype=x.dtype))
            angle = (x[:, :, None] * scale).flatten(1)  # [N_0, 3 F]
            parts += [angle.sin(), angle.cos()]
        return torch.cat(parts, dim=-1) if parts else None

    def latent(self, data: HierarchicalData) -> Tensor:
        """The latent code of every ``l0`` node from one V-cycle over the initial state, ``[N_0, d]``.

        With ``settings_input`` the fine nodes also read the normalised settings (the grippers'
        positions and forces at :math:`t = 0`; the decoder reads them too).
        """
        x_dict, e_dict = self._raw_features(data)
        x_dict = {lk: self.node_norm["fine" if lk == "l0" else "coarse"](x) for lk, x in x_dict.items()}
        if self.base_input_norm is not None:
            steps = self._base_input_steps().to(x_dict["l0"].device)
            base = self._base(data, steps).flatten(1)  # [N_0, 3 k]
            x_dict["l0"] = torch.cat([x_dict["l0"], self.base_input_norm(base)], dim=-1)
        e_dict = {key: self.edge_norm[key[1]](e) for key, e in e_dict.items()}
        empty = torch.empty(2, 0, dtype=torch.long, device=data["l0"].pos.device)
        index_dict = {key: data[key].edge_index if key in data.edge_types else empty for key in e_dict}
        batch_dict = None
        if "batch" in data["l0"]:
            batch_dict = {level_name(k): data[level_name(k)].batch for k in range(self.num_levels)}
        return self.model(x_dict, index_dict, e_dict, batch_dict=batch_dict)

    def _decode(
        self,
        data: HierarchicalData,
        h: Tensor,
        t: Tensor,
        mask: Tensor | None = None,
        base: Tensor | None = None,
    ) -> Tensor:
        """The normalised departure of the (``mask``-ed) ``l0`` nodes at times ``t [S]``, ``[N, S, 3]``.

        ``base [N_0, S, 3]``: the mean base at those times (read by the decoder with ``base_input``).
        """
        cond = self._condition(data)
        point = None
        if self.base_point_norm is not None:
            if base is None:
                raise ValueError("base_input: the decoder reads the mean base at the asked times; none given")
            point = self.base_point_norm(base)
        if mask is not None:
            h, cond = h[mask], None if cond is None else cond[mask]
            point = None if point is None else point[mask]
        out = self.decoder(h, t, cond, point)
        if self.modes is not None:
            fine = data["l0"]
            batch = fine.batch if "batch" in fine else None
            settings = (
                self.settings_norm(self._settings(data))
                if self.settings_input
                else torch.zeros(int(data.gripper_pos.size(0)), 1, device=h.device)
            )  # [B, c]
            if mask is not None and batch is not None:
                batch = batch[mask]
            out = out + self.modes(h, settings, t, batch)
        return out

    @staticmethod
    def _prior(data: HierarchicalData) -> Tensor:
        """The prior's displacement of every ``l0`` node and saved step, ``[N_0, T, 3]``."""
        fine = data["l0"]
        if "prior_displacement" not in fine:
            raise ValueError(
                "base='prior': the sample has no prior trajectory (l0.prior_displacement); "
                "set data.prior (e.g. pod_gp), or give the trajectories a prior"
            )
        return fine.prior_displacement.float()

    def _base(self, data: HierarchicalData, steps: Tensor) -> Tensor | None:
        """The base's displacement at ``steps`` (1-based) of every ``l0`` node ``[N_0, S, 3]``.

        The mean training displacement (``base="mean"``), the sample's prior (``"prior"``), or
        ``None`` (``"initial"``).
        """
        if self.base == "prior":
            return self._prior(data)[:, steps - 1]
        if self.base != "mean":
            return None
        if self.base_norm is None:
            raise RuntimeError("the mean base is unknown: accumulate and freeze the statistics first")
        num_steps, nodes = self.base_shape
        n = data["l0"].num_nodes
        if n % nodes:
            raise ValueError(
                f"base='mean' was fitted on a mesh of {nodes} nodes; this one has {n} "
                "(a model with base='initial' takes other meshes)"
            )
        mean = self.base_norm.running_mean.reshape(num_steps, nodes, 3).float()[steps - 1]  # [S, N, 3]
        return mean.transpose(0, 1).repeat(n // nodes, 1, 1)  # [N_0, S, 3]

    def _departure_scale(self, data: HierarchicalData, steps: Tensor) -> Tensor | None:
        """The ``step`` or ``node_step`` scale of the departure at ``steps`` (1-based), ``[N_0, S, 3]``.

        The training spread about the mean base (from its statistics); ``None`` for ``"global"``.
        """
        if self.target_scale == "global":
            return None
        if self.base_norm is None:
            raise RuntimeError("the mean base is unknown: accumulate and freeze the statistics first")
        num_steps, nodes = self.base_shape
        var = self.base_norm.running_m2.reshape(num_steps, nodes, 3) / self.base_norm.count.clamp_min(1)
        if self.target_scale == "step":  # the mean over nodes (tool nodes, fixed, only scale it)
            var = var.mean(1, keepdim=True).expand(num_steps, nodes, 3)
        floor = 1e-2 * var.mean((0, 1)).sqrt()  # [3]: 1 % of the global spread
        scale = (var + floor.square()).sqrt().float()[steps - 1]  # [S, N, 3]
        return scale.transpose(0, 1).repeat(data["l0"].num_nodes // nodes, 1, 1)  # [N_0, S, 3]

    def _check_steps(self, num_steps: int) -> None:
        if self.base == "mean" and num_steps != self.base_shape[0]:
            raise ValueError(
                f"base='mean' was fitted on trajectories of {self.base_shape[0]} steps, not {num_steps}"
            )

    def predict_displacement(
        self, data: HierarchicalData, num_steps: int, steps: Tensor | None = None
    ) -> Tensor:
        r"""Displacement :math:`x^t - x^0` in mm of every ``l0`` node at ``steps``, ``[N_0, S, 3]``.

        Args:
            data: Initial-state samples (one or a batch).
            num_steps: Saved steps ``T`` of the trajectory (times are ``steps / T``).
            steps: The steps ``LongTensor[S]`` in ``1..T`` (default: all).
        """
        self._check_steps(num_steps)
        device = data["l0"].pos.device
        steps = torch.arange(1, num_steps + 1, device=device) if steps is None else steps.to(device)
        base = self._base(data, steps)
        out = self._decode(data, self.latent(data), steps / num_steps, base=base)
        scale = self._departure_scale(data, steps)
        out = self.target_norm.denormalize(out) if scale is None else out * scale
        return out if base is None else out + base

    def loss(self, data: HierarchicalData, generator: torch.Generator | None = None) -> Tensor:
        """MSE of the normalised departure from the base over ply nodes and (``loss_steps`` random) steps."""
        fine = data["l0"]
        num_steps = fine.displacement.size(1)
        self._check_steps(num_steps)
        steps = torch.arange(1, num_steps + 1, device=fine.pos.device)
        if self.loss_steps is not None and self.loss_steps < num_steps:
            pick = torch.randperm(num_steps, generator=generator)[: self.loss_steps].sort().values
            steps = steps[pick.to(steps.device)]
        ply = fine.ply_mask
        target = fine.displacement[ply][:, steps - 1]  # [N_ply, S, 3]
        base = self._base(data, steps)
        if base is not None:
            target = target - base[ply]
        out = self._decode(data, self.latent(data), steps / num_steps, ply, base)  # [N_ply, S, 3]
        scale = self._departure_scale(data, steps)
        target = self.target_norm(target) if scale is None else target / scale[ply]
        return (out - target).square().mean()

    def extra_repr(self) -> str:
        """Data sizes shown by ``repr``."""
        return (
            f"num_components={self.num_components}, num_grippers={self.num_grippers}, base={self.base!r}, "
            f"target_scale={self.target_scale!r}"
        )
