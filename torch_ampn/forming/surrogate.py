"""AMPNSurrogate: features, normalisation and the (diffusion) AMPN as one next-step predictor."""

from __future__ import annotations

from collections.abc import Callable, Sequence
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
from torch_ampn.nn.ampn import EdgeType
from torch_ampn.nn.diffusion import DiffusionAMPN, RobinAMPN
from torch_ampn.nn.multilevel_loss import multilevel_mse
from torch_ampn.transforms.contact import ComponentRadiusGraph
from torch_ampn.utils.imports import import_object


class AMPNSurrogate(ModelFile, nn.Module):
    r"""Next-step predictor of ply displacements: features -> normalisation -> AMPN -> residual in mm.

    It owns everything a checkpoint needs to roll out a trajectory: the network (an
    :class:`~torch_ampn.nn.RobinAMPN` wrapped in :class:`~torch_ampn.nn.DiffusionAMPN`; ``K = 1`` is plain
    AMPN), the :class:`~torch_ampn.forming.Normalizer` of every input kind and of the target (statistics from
    training data, saved in the state dict) and the contact-edge settings
    (:attr:`contact`, a :class:`~torch_ampn.transforms.ComponentRadiusGraph`).

    Inputs are :class:`~torch_ampn.data.HierarchicalData` windows as made by
    :func:`~torch_ampn.data.step_sample` (one or a ``Batch``), with contact edges filled.

    Args:
        num_components: Components of the mesh ``C`` (plies and tools; 6 for the default dataset);
            with ``component_encoding="stack"`` the most of any part (contact tables have
            ``k (C - 1)`` slots, unused ones masked).
        num_grippers: Grippers ``G`` (2 for the default dataset).
        num_levels: Levels of the V-cycle, ``L + 1`` (paper: 4; 1 = flat MeshGraphNet baseline).
        diffusion_steps: ``K`` of ROBIN mode; 1 = AMPN with the plain MSE objective.
        contact_radius: Contact radius ``r`` (mm).
        contact_k: Contact neighbours per other component.
        contact_mode: ``"component_knn"`` (the paper) or ``"radius"`` (every node within ``r``,
            any component); see :class:`~torch_ampn.transforms.ComponentRadiusGraph`.
        contact_positions: ``"current"`` (the paper: edges rebuilt from the positions of every
            step) or ``"initial"`` (edges from the initial state, kept for the whole rollout: ROBIN).
        level_radius_scale: Per-level radius scale of the contact edges (see
            :class:`~torch_ampn.transforms.ComponentRadiusGraph`).
        gripper_alpha: Distance decay :math:`\alpha` of the gripper features.
        center_target: Standardise the target residual (subtract its training mean) or only
            scale it, so that a zero network output means "this node stays where it is".
        predict_change: Let the network predict the change of the residual,
            :math:`\Delta u^t - \Delta u^{t-1}` (normalised with its own statistics), and add the
            previous residual back (:meth:`predict_residual` always returns :math:`\Delta u^t`).
            A zero output then means "keep moving as in the last step", as MeshGraphNets'
            acceleration targets do. ``False`` is the paper's residual target.
        huber_delta: Huber form of the squared error beyond this normalised error
            (:func:`~torch_ampn.nn.diffusion.pointwise_loss`); ``None``: plain MSE (the paper).
        coarse_loss_weight: :math:`\lambda` of the multilevel loss
            (:func:`~torch_ampn.nn.multilevel_mse`): the squared errors of the residual error
            restricted to every coarse level are added with this weight; 0 (the paper): plain MSE.
        component_encoding: How a node's component enters its features
            (:func:`~torch_ampn.forming.features.component_features`): ``"onehot"`` (the paper's, one
            part) or ``"stack"`` (a ply's place in its stack: the same on parts of any ply count).
        prior_features: Take a prior prediction of the trajectory as input
            (:func:`~torch_ampn.forming.features.prior_features`: 6 more fine-node columns), so that
            the network learns a correction of the prior; the windows must then carry it
            (:attr:`~torch_ampn.data.Trajectory.prior`; rollouts read it from there too).
        prior_base: With ``prior_features``: the network learns the departure of each step from
            the prior's step, :math:`\Delta u^t - (p^t - p^{t-1})` (normalised with its own
            statistics), and the prior's step is added back, as a direct model's
            ``base="prior"`` does; with a setting-independent prior (the mean training
            trajectory) the network's whole target is then what the settings change. ``False``:
            the prior is an input only. Rollouts take the plain path.
        network_class: Another network in place of the AMPN, as ``"package.module:Class"`` (e.g.
            a peer's model behind an adapter, ``benchmarks/peers.py``). It is built as
            ``Class(fine_in_channels, num_levels=..., noise_channels=3, num_step_frequencies=...,
            max_step=..., **network_options)`` and called like :meth:`RobinAMPN.forward
            <torch_ampn.nn.RobinAMPN.forward>`; it must have the attributes ``noise_channels``,
            ``out_channels``, ``step_encoding`` (``None`` without step conditioning) and
            ``num_layers``. With ``needs_positions = True`` on the class, ``x_dict`` also
            carries the normalised current and initial ``l0`` positions (``"pos"``, ``"pos0"``,
            ``[N_0, 3]``). The AMPN's own arguments (``**network``) are then unused. Rollouts of
            such a network take the plain path (:func:`~torch_ampn.rollout.rollout`).
        network_options: Keyword arguments of ``network_class``.
        bundle_steps: Temporal bundling (Brandstetter et al., 2022): one call predicts the next
            ``B`` saved steps, so a rollout of ``T`` steps takes ``ceil(T / B)`` calls and its
            errors compound ``B`` times less often. The target is then the offsets
            :math:`x^{t-1+k} - x^{t-1}`, ``k = 1 .. B`` (``[N, 3 B]``), and the prescribed tool
            motion of the ``B`` steps is an input (:func:`~torch_ampn.data.step_sample`). 1 (the
            paper): the next step only. Not with ``predict_change``, ``prior_features`` or
            ``network_class``; rollouts take the plain path.
        **network: Further arguments of :class:`~torch_ampn.nn.RobinAMPN`: ``hidden_channels``,
            ``mlp_channels``, the layer counts of the five stacks and ``aggr`` (the paper's values
            by default). The noise input and the diffusion-step encoding are set here.
    """

    def __init__(
        self,
        num_components: int = 6,
        num_grippers: int = 2,
        num_levels: int = 4,
        diffusion_steps: int = 1,
        contact_radius: float = 3.0,
        contact_k: int = 3,
        contact_mode: str = "component_knn",
        contact_positions: str = "current",
        level_radius_scale: float | Sequence[float] | None = None,
        gripper_alpha: float = 3e-2,
        center_target: bool = True,
        predict_change: bool = False,
        huber_delta: float | None = None,
        coarse_loss_weight: float = 0.0,
        component_encoding: str = "onehot",
        prior_features: bool = False,
        prior_base: bool = False,
        network_class: str | None = None,
        network_options: dict[str, Any] | None = None,
        bundle_steps: int = 1,
        **network: Any,
    ) -> None:
        super().__init__()
        arguments = {k: v for k, v in locals().items() if k not in ("self", "__class__", "network")}
        #: The constructor's arguments (what :meth:`save` writes; :meth:`load` builds from them).
        self.arguments: dict[str, Any] = {**arguments, **network}
        #: What a model file carried besides the weights (:meth:`load`; e.g. its training meshes).
        self.meta: dict[str, Any] = {}
        if huber_delta is not None and huber_delta <= 0:
            raise ValueError(f"huber_delta must be positive or None, got {huber_delta}")
        if coarse_loss_weight < 0:
            raise ValueError(f"coarse_loss_weight must be >= 0, got {coarse_loss_weight}")
        if coarse_loss_weight > 0 and huber_delta is not None:
            raise ValueError("coarse_loss_weight > 0 needs the plain squared error (huber_delta=None)")
        if num_components < 1:
            raise ValueError(f"num_components must be >= 1, got {num_components}")
        if diffusion_steps < 1:
            raise ValueError(f"diffusion_steps must be >= 1, got {diffusion_steps}")
        check_bundle_steps(bundle_steps, predict_change, prior_features, network_class)
        if prior_base and not prior_features:
            raise ValueError(
                "prior_base needs prior_features (and a data.prior): the prior's step is the base"
            )
        if prior_base and predict_change:
            raise ValueError("prior_base and predict_change are two bases of the step: use one")
        self.prior_base = bool(prior_base)
        self.bundle_steps = bundle_steps
        self.num_components = num_components
        self.num_grippers = num_grippers
        self.num_levels = num_levels
        self.gripper_alpha = gripper_alpha
        self.predict_change = predict_change
        self.huber_delta = huber_delta
        self.coarse_loss_weight = coarse_loss_weight
        self.component_encoding = component_encoding
        self.prior_features = bool(prior_features)
        self.contact = ComponentRadiusGraph(
            r=contact_radius,
            k=contact_k,
            level_radius_scale=level_radius_scale,
            num_components=num_components,
            mode=contact_mode,
            positions=contact_positions,
        )
        sizes = ampn_channels(
            num_components,
            num_grippers,
            component_encoding=component_encoding,
            prior=self.prior_features,
            bundle_steps=bundle_steps,
        )
        fine_in = sizes["fine_in_channels"]
        self.network_class = network_class
        out = 3 * bundle_steps  # the residual, or the offsets of the B bundled steps
        common = {
            "num_levels": num_levels,
            "noise_channels": out,  # ROBIN's noise input: the noisy target (K = 1: pure N(0, 1) noise)
            "num_step_frequencies": 4 if diffusion_steps > 1 else 0,
            "max_step": max(diffusion_steps - 1, 1),
        }
        if network_class is None:
            model = RobinAMPN(**sizes, **common, out_channels=out, **network)
        else:
            model = import_network_class(network_class)(fine_in, **common, **(network_options or {}))
        self.diffusion = DiffusionAMPN(model, diffusion_steps)
        self.node_norm = nn.ModuleDict(
            {"fine": Normalizer(fine_in), "coarse": Normalizer(num_coarse_node_features())}
        )
        self.edge_norm = nn.ModuleDict({rel: Normalizer(num_edge_features(rel)) for rel in RELATIONS})
        self.target_norm = Normalizer(out, center=center_target)
        self.position_norm = Normalizer(3)

    @property
    def model(self) -> RobinAMPN:
        """The network (a :class:`~torch_ampn.nn.RobinAMPN` unless ``network_class`` is set)."""
        return self.diffusion.model

    @property
    def diffusion_steps(self) -> int:
        """``K``."""
        return self.diffusion.num_steps

    # ---- statistics --------------------------------------------------------------------
    def _normalizers(self) -> list[Normalizer]:
        return [*self.node_norm.values(), *self.edge_norm.values(), self.target_norm, self.position_norm]

    @property
    def statistics_frozen(self) -> bool:
        """Whether the normalisation statistics are final (after :meth:`freeze_statistics`)."""
        return all(bool(n.frozen) for n in self._normalizers())

    @torch.no_grad()
    def accumulate_statistics(self, data: HierarchicalData) -> None:
        """Add a training window (or batch) to the statistics of every normaliser."""
        x_dict, e_dict = self._raw_features(data)
        for lk, x in x_dict.items():
            self.node_norm["fine" if lk == "l0" else "coarse"].update(x)
        for (_, rel, _), e in e_dict.items():
            self.edge_norm[rel].update(e)
        fine = data["l0"]
        self.target_norm.update(self._network_target(fine)[fine.ply_mask])
        self.position_norm.update(fine.pos)

    def freeze_statistics(self) -> None:
        """Freeze every normaliser (later :meth:`accumulate_statistics` calls raise)."""
        for n in self._normalizers():
            n.freeze()

    @property
    def position_std(self) -> float:
        r""":math:`\sigma_x`: the standard deviation of training node positions (mean over axes)."""
        return float(self.position_norm.std.mean())

    # ---- features ----------------------------------------------------------------------
    def _check_levels(self, data: HierarchicalData) -> None:
        if data.num_levels < self.num_levels:
            raise ValueError(
                f"the model uses {self.num_levels} levels but the hierarchy has only {data.num_levels}; "
                "build a deeper hierarchy (smaller min_coarse_nodes) or lower num_levels"
            )

    def _raw_features(self, data: HierarchicalData) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """The paper's features of the used levels with this model's settings, not normalised."""
        self._check_levels(data)
        return hierarchical_features(
            data,
            self.num_components,
            self.num_levels,
            alpha=self.gripper_alpha,
            component_encoding=self.component_encoding,
            prior=self.prior_features,
        )

    def normalize(
        self, x_dict: dict[str, Tensor], edge_attr_dict: dict[EdgeType, Tensor]
    ) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """Normalised node and edge features (of :func:`~torch_ampn.forming.step_features`), same keys."""
        x_dict = {lk: self.node_norm["fine" if lk == "l0" else "coarse"](x) for lk, x in x_dict.items()}
        return x_dict, {key: self.edge_norm[key[1]](e) for key, e in edge_attr_dict.items()}

    def normalized_features(
        self, data: HierarchicalData
    ) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor], dict[EdgeType, Tensor]]:
        """``(x_dict, edge_index_dict, edge_attr_dict)`` of the used levels, normalised."""
        x_dict, e_dict = self.normalize(*self._raw_features(data))
        if getattr(self.model, "needs_positions", False):
            fine = data["l0"]
            x_dict["pos"] = self.position_norm(fine.pos)  # [N_0, 3]
            x_dict["pos0"] = self.position_norm(fine.pos0)  # [N_0, 3]
        device = data["l0"].pos.device
        empty = torch.empty(2, 0, dtype=torch.long, device=device)
        index_dict = {key: data[key].edge_index if key in data.edge_types else empty for key in e_dict}
        return x_dict, index_dict, e_dict

    @staticmethod
    def _batch_dict(data: HierarchicalData, num_levels: int) -> dict[str, Tensor] | None:
        if "batch" not in data["l0"]:
            return None
        return {level_name(k): data[level_name(k)].batch for k in range(num_levels)}

    # ---- training and inference -------------------------------------------------------
    def _network_target(self, fine) -> Tensor:
        """What the network learns, in mm ``[N_0, 3]``: the residual, less the base if it has one."""
        return fine.target - self._base(fine) if self.predict_change or self.prior_base else fine.target

    def _base(self, fine) -> Tensor:
        """The step's base ``[N_0, 3]`` mm: the prior's step (``prior_base``) or the previous residual."""
        if self.prior_base:
            return fine.prior_next - fine.prior_pos
        return fine.prev_disp

    def loss(
        self,
        data: HierarchicalData,
        generator: torch.Generator | None = None,
        network: nn.Module | None = None,
    ) -> Tensor:
        """Training loss on the ply nodes of a window (batch): MSE on the normalised residual (ROBIN: on v).

        With ``huber_delta`` the squared error becomes its Huber form beyond that error; with
        ``coarse_loss_weight`` the restricted errors of the coarse levels are added
        (:func:`~torch_ampn.nn.multilevel_mse`).
        ``network`` runs in place of the AMPN (e.g. its ``torch.compile`` wrapper; see
        :meth:`DiffusionAMPN.loss`).

        ``data["l0"].target`` is the residual in mm and ``data["l0"].ply_mask`` selects the predicted nodes.
        """
        x_dict, index_dict, e_dict = self.normalized_features(data)
        fine = data["l0"]
        target = self.target_norm(self._network_target(fine))
        args = (target, x_dict, index_dict, e_dict)
        batch_dict = self._batch_dict(data, self.num_levels)
        if self.coarse_loss_weight == 0:
            return self.diffusion.loss(
                *args, batch_dict=batch_dict, node_mask=fine.ply_mask, generator=generator,
                huber_delta=self.huber_delta, network=network,
            )  # fmt: skip
        error = self.diffusion.error(*args, batch_dict=batch_dict, generator=generator, network=network)
        down = [
            (data.down(k).edge_index, data.down(k).edge_weight, data[level_name(k + 1)].num_nodes)
            for k in range(self.num_levels - 1)
        ]
        return multilevel_mse(error, fine.ply_mask, down, self.coarse_loss_weight)

    def predict_residual(self, data: HierarchicalData, generator: torch.Generator | None = None) -> Tensor:
        r"""Predicted residual :math:`\Delta u^t` in mm of every ``l0`` node, ``[N_0, 3]`` (K-step sampling).

        A bundled model (``bundle_steps`` ``B > 1``) returns the offsets
        :math:`x^{t-1+k} - x^{t-1}` of the next ``B`` steps, ``[N_0, 3 B]``.
        Tool rows are whatever the network says; callers replace them by the prescribed motion.
        """
        x_dict, index_dict, e_dict = self.normalized_features(data)
        fine = data["l0"]
        base = self._base(fine) if self.prior_base else None
        return self.residual_from_features(
            x_dict, index_dict, e_dict, fine.prev_disp, generator=generator, base=base
        )

    def residual_from_features(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict[EdgeType, Tensor],
        edge_attr_dict: dict[EdgeType, Tensor],
        prev_disp: Tensor,
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
        generator: torch.Generator | None = None,
        network: nn.Module | None = None,
        draw: Callable[[], Tensor] | None = None,
        base: Tensor | None = None,
    ) -> Tensor:
        r""":meth:`predict_residual` from normalised features (:meth:`normalized_features`), ``[N_0, 3]`` mm.

        Args:
            x_dict: Normalised node features.
            edge_index_dict: Edge indices (contact: an edge list, or every slot of a fixed-size
                table with ``contact_mask_dict``).
            edge_attr_dict: Normalised edge features.
            prev_disp: :math:`\Delta u^{t-1}` of the ``l0`` nodes ``[N_0, 3]`` (used with ``predict_change``).
            contact_mask_dict: Validity of the contact slots (see :meth:`~torch_ampn.nn.AMPN.forward`).
            generator: Random generator of the sampling noise.
            network: Runs in place of the AMPN (e.g. compiled).
            draw: Noise source in place of ``generator`` (see :meth:`DiffusionAMPN.sample`).
            base: The prior's step :math:`p^t - p^{t-1}` ``[N_0, 3]`` (needed with ``prior_base``).
        """
        out = self.diffusion.sample(
            x_dict, edge_index_dict, edge_attr_dict, contact_mask_dict,
            generator=generator, network=network, draw=draw,
        )  # fmt: skip
        residual = self.target_norm.denormalize(out.float())
        if self.predict_change:
            residual = residual + prev_disp.to(residual.dtype)
        if self.prior_base:
            if base is None:
                raise ValueError("a prior_base model needs the prior's step: pass base")
            residual = residual + base.to(residual.dtype)
        return residual

    def extra_repr(self) -> str:
        """Data sizes shown by ``repr``."""
        encoding = self.component_encoding
        return (
            f"num_components={self.num_components}, num_grippers={self.num_grippers}, "
            f"diffusion_steps={self.diffusion_steps}"
            + (", predict_change=True" if self.predict_change else "")
            + (f", component_encoding={encoding!r}" if encoding != "onehot" else "")
            + (", prior_features=True" if self.prior_features else "")
            + (", prior_base=True" if self.prior_base else "")
            + (f", bundle_steps={self.bundle_steps}" if self.bundle_steps > 1 else "")
            + (f", network_class={self.network_class!r}" if self.network_class else "")
        )


def check_bundle_steps(
    bundle_steps: int,
    predict_change: bool = False,
    prior_features: bool = False,
    network_class: str | None = None,
) -> None:
    """One-line errors for a ``bundle_steps`` an :class:`AMPNSurrogate` cannot have."""
    if not isinstance(bundle_steps, int) or bundle_steps < 1:
        raise ValueError(f"bundle_steps must be an integer >= 1, got {bundle_steps!r}")
    if bundle_steps == 1:
        return
    for name, used in (
        ("predict_change", predict_change),
        ("prior_features", prior_features),
        ("network_class", network_class is not None),
    ):
        if used:
            raise ValueError(f"bundle_steps > 1 does not work with {name}: use one or the other")


def import_network_class(path: str) -> type[nn.Module]:
    """The class ``"package.module:Class"`` (or ``"package.module.Class"``) names; one-line errors."""
    cls = import_object(path, "network_class")
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ValueError(f"network_class: {path!r} is not a torch.nn.Module class")
    return cls
