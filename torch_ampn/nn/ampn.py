"""AMPN: the algebraic-hierarchical message passing network (V-cycle) of the seed paper."""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch
from torch import Tensor, nn
from torch_geometric.nn.aggr import Aggregation

from torch_ampn.hierarchy.hierarchical_data import CONTACT, DOWN, MESH, UP, EdgeType, edge_type, level_name
from torch_ampn.nn._conv import check_aggr
from torch_ampn.nn.encoding import FourierLevelEncoding
from torch_ampn.nn.inter_level_conv import InterLevelConv
from torch_ampn.nn.intra_level_conv import IntraLevelConv
from torch_ampn.nn.slots import split_edges


class AMPN(nn.Module):
    r"""Algebraic-hierarchical message passing network (seed paper, "Processor and decoder").

    **Encoder.** One linear layer per node kind (fine ``l0`` nodes; coarse ``l1 .. lL``
    nodes) and per edge kind (mesh, contact, down, up) maps the (normalised) input
    features to :math:`d` = ``hidden_channels``. The input of a node is its features, for
    ``l0`` nodes followed by the noise input (``noise_channels`` columns), followed by the
    :class:`FourierLevelEncoding` of its level and, with ``num_step_frequencies > 0``, the
    encoding of the diffusion step.

    **Processor (V-cycle).** Five stacks whose weights are shared by all levels:
    Pre (``pre_layers`` :class:`IntraLevelConv`), Down (``down_layers``
    :class:`InterLevelConv`), Solve (``solve_layers`` intra), Post (``post_layers`` intra)
    and Up (``up_layers`` inter), 3 + 2 + 5 + 3 + 2 = 15 layers with the paper's values.
    For ``l = 0 .. L-1``: Pre on level ``l``, then Down from ``l`` to ``l+1`` (fine
    sources, coarse targets). On the coarsest level ``L``: Pre, Solve, Post. For
    ``l = L-1 .. 0``: Up from ``l+1`` to ``l`` (updating the level-``l`` embeddings kept
    from the way down), then Post on level ``l``. Mesh and contact edge embeddings of a
    level carry over from its Pre to its Post stack; down and up edges have their own.
    Changing ``num_levels`` (for ``num_levels >= 2``) changes no parameter count.

    **Decoder.** A linear layer on the final ``l0`` embeddings gives the (normalised)
    residual :math:`\Delta u^t`, ``[N_0, out_channels]``.

    **Flat baseline** (``num_levels=1``): a MeshGraphNet-style processor on ``l0`` only:
    Pre, Solve, Post (``3 + 5 + 3 = 11`` :class:`IntraLevelConv` layers with mesh and contact
    edges); the Down/Up stacks and the coarse-node, down- and up-edge encoders are not
    created (they would receive no gradient).

    The forward pass is compile-friendly: the level loop is static (``num_levels`` is fixed
    per model), there is no ``.item()`` and no boolean indexing; fixed-size contact tables
    with a validity mask give static shapes.

    Args:
        fine_in_channels: Node features of ``l0``, without the noise input.
        coarse_in_channels: Node features of coarse levels.
        edge_channels: Input features of every edge relation: one number for all, or one
            per relation ``{"mesh": ..., "contact": ..., "down": ..., "up": ...}`` (down and
            up only with ``num_levels > 1``). The forming surrogate's sizes are
            :func:`torch_ampn.forming.ampn_channels`.
        out_channels: Size of the prediction per ``l0`` node (3: the residual).
        hidden_channels: Latent size :math:`d` of node and edge embeddings.
        num_levels: Levels used, ``L + 1`` (paper: 4); ``1`` is the flat baseline. The
            input may hold more levels (the coarser ones are ignored), not fewer.
        pre_layers: Layers of the Pre stack.
        down_layers: Layers of the Down stack.
        solve_layers: Layers of the Solve stack.
        post_layers: Layers of the Post stack.
        up_layers: Layers of the Up stack.
        aggr: Aggregation of all layers: ``"max"``, ``"sum"``, ``"mean"`` or a
            ``torch_geometric.nn.aggr.Aggregation`` (each layer gets its own copy, so a
            learnable aggregation is learnt per layer).
        mlp_channels: Hidden width of the layer MLPs (paper: 128, whatever :math:`d` is).
        noise_channels: Columns of a noise input appended to the ``l0`` features; the caller
            passes it to :meth:`forward` (ROBIN mode: the noisy target, see
            :class:`~torch_ampn.nn.DiffusionAMPN`). ``0`` (default): no noise input, and the
            output is a deterministic function of the input.
        num_level_frequencies: Frequencies of the level encoding (``2 F`` inputs).
        num_step_frequencies: Frequencies of the diffusion-step encoding; ``0`` (default)
            for a model without step conditioning (AMPN, ``K = 1``).
        max_step: Largest diffusion-step index the step encoding separates.
    """

    def __init__(
        self,
        fine_in_channels: int,
        coarse_in_channels: int,
        edge_channels: int | Mapping[str, int],
        out_channels: int = 3,
        hidden_channels: int = 128,
        num_levels: int = 4,
        pre_layers: int = 3,
        down_layers: int = 2,
        solve_layers: int = 5,
        post_layers: int = 3,
        up_layers: int = 2,
        aggr: str | Aggregation = "max",
        mlp_channels: int = 128,
        noise_channels: int = 0,
        num_level_frequencies: int = 4,
        num_step_frequencies: int = 0,
        max_step: int = 20,
    ) -> None:
        super().__init__()
        if num_levels < 1:
            raise ValueError(f"num_levels must be >= 1, got {num_levels}")
        if num_levels > 1 and (down_layers < 1 or up_layers < 1):
            raise ValueError("a hierarchy (num_levels > 1) needs down_layers >= 1 and up_layers >= 1")
        self.fine_in_channels = fine_in_channels
        self.coarse_in_channels = coarse_in_channels
        self.out_channels = out_channels
        self.hidden_channels = hidden_channels
        self.num_levels = num_levels
        aggr = check_aggr(aggr)
        self.aggr = aggr if isinstance(aggr, str) else repr(aggr)  # a template module is not registered
        self.mlp_channels = mlp_channels
        self.noise_channels = noise_channels

        self.level_encoding = FourierLevelEncoding(num_level_frequencies, max_index=8.0)
        self.step_encoding = (
            FourierLevelEncoding(num_step_frequencies, max_index=float(max_step))
            if num_step_frequencies > 0
            else None
        )
        cond = self.level_encoding.out_channels + (
            self.step_encoding.out_channels if self.step_encoding is not None else 0
        )
        d, h = hidden_channels, self.mlp_channels
        hierarchical = num_levels > 1

        fine_in = fine_in_channels + self.noise_channels + cond
        self.node_encoders = nn.ModuleDict({"fine": nn.Linear(fine_in, d)})
        widths = _edge_channels(edge_channels, (MESH, CONTACT, DOWN, UP) if hierarchical else (MESH, CONTACT))
        self.edge_encoders = nn.ModuleDict({rel: nn.Linear(widths[rel], d) for rel in (MESH, CONTACT)})
        if hierarchical:  # (created in this order, which the initialisation's random draws follow)
            self.node_encoders["coarse"] = nn.Linear(coarse_in_channels + cond, d)
            self.edge_encoders[DOWN] = nn.Linear(widths[DOWN], d)
            self.edge_encoders[UP] = nn.Linear(widths[UP], d)

        def stack(conv: type[IntraLevelConv | InterLevelConv], n: int) -> nn.ModuleList:
            return nn.ModuleList(conv(d, h, copy.deepcopy(aggr)) for _ in range(n))

        self.pre = stack(IntraLevelConv, pre_layers)
        self.solve = stack(IntraLevelConv, solve_layers)
        self.post = stack(IntraLevelConv, post_layers)
        self.down = stack(InterLevelConv, down_layers) if hierarchical else nn.ModuleList()
        self.up = stack(InterLevelConv, up_layers) if hierarchical else nn.ModuleList()
        self.decoder = nn.Linear(d, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Reset all learnable parameters."""
        for module in (*self.node_encoders.values(), *self.edge_encoders.values(), self.decoder):
            module.reset_parameters()
        for stack in (self.pre, self.down, self.solve, self.post, self.up):
            for conv in stack:
                conv.reset_parameters()

    @property
    def num_layers(self) -> int:
        """Number of learnable message passing layers (15 with the paper's values)."""
        return sum(len(s) for s in (self.pre, self.down, self.solve, self.post, self.up))

    # ---- forward -----------------------------------------------------------------------
    def _conditioning(
        self, level: int, num_nodes: int, step_code: Tensor | None, batch: Tensor | None, like: Tensor
    ) -> list[Tensor]:
        """Level (and step) encodings of ``num_nodes`` nodes of ``level``: list of ``[N, *]``."""
        out = [self.level_encoding(level).to(like.dtype).expand(num_nodes, -1)]  # [N, 2F]
        if step_code is not None:
            if step_code.dim() == 2 and batch is not None:  # [B, 2F']: a step per graph
                code = step_code[batch]
            else:  # [2F'] or [1, 2F']: the same step everywhere
                code = step_code.expand(num_nodes, -1)
            out.append(code.to(like.dtype))
        return out

    def forward(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict[EdgeType, Tensor],
        edge_attr_dict: dict[EdgeType, Tensor],
        noise: Tensor | None = None,
        step: Tensor | None = None,
        batch_dict: dict[str, Tensor] | None = None,
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
    ) -> Tensor:
        """Predict the (normalised) residual of the ``l0`` nodes.

        Inputs are keyed like a :class:`~torch_ampn.data.HierarchicalData`
        (``data.edge_index_dict``, ``data.batch_dict``); build the features with
        :func:`~torch_ampn.forming.hierarchical_features` and normalise them.

        Args:
            x_dict: Node features ``{"lk": [N_k, F_k]}`` for ``k < num_levels``
                (``fine_in_channels`` for ``l0``, ``coarse_in_channels`` otherwise).
            edge_index_dict: ``{(src, rel, dst): LongTensor[2, E]}`` rows ``(source, target)``:
                ``("lk", "mesh", "lk")`` and ``("lk", "contact", "lk")`` for every used level
                (a missing contact set counts as empty), ``("lk", "down", "lk+1")`` and
                ``("lk+1", "up", "lk")`` between used levels. Other keys are ignored. Any
                of them may be a :class:`~torch_ampn.nn.SlottedEdgeIndex` (the edges with
                their aggregation table; what :class:`~torch_ampn.rollout.fast.FastRollout`
                passes): those aggregate by a dense reduction (same result).
            edge_attr_dict: Edge features with the same keys.
            noise: Noise input of ``l0`` ``[N_0, noise_channels]`` (models with
                ``noise_channels > 0`` only): the noisy target in ROBIN mode, N(0, 1) samples
                in the paper's AMPN mode.
            step: Diffusion-step index (models with step conditioning only): a number or
                scalar tensor (every graph) or ``LongTensor[B]`` (one per graph, with ``batch_dict``).
            batch_dict: ``{"lk": LongTensor[N_k]}`` graph of every node; needed only for a
                per-graph ``step``.
            contact_mask_dict: Optional ``{("lk", "contact", "lk"): BoolTensor[M_k]}``
                validity masks of fixed-size contact tables (see :class:`IntraLevelConv`).

        Returns:
            ``[N_0, out_channels]``.
        """
        num_levels = self.num_levels
        names = [level_name(k) for k in range(num_levels)]
        for lk in names:
            if lk not in x_dict:
                raise KeyError(f"AMPN with num_levels={num_levels} needs node features for {lk!r}")
        if self.noise_channels > 0 and noise is None:
            raise ValueError(
                f"this AMPN has a noise input ({self.noise_channels} channels): pass `noise` "
                "(or build it with noise_channels=0)"
            )
        step_code = None
        if self.step_encoding is not None:
            if step is None:
                raise ValueError("this AMPN is conditioned on the diffusion step: pass `step`")
            step_code = self.step_encoding(step)  # [2F'] or [B, 2F']
        batch_dict = batch_dict or {}

        # ---- encode ------------------------------------------------------------------
        h: list[Tensor] = []  # node embeddings per level, [N_k, d]
        for k, lk in enumerate(names):
            x = x_dict[lk]
            parts = [x]
            if k == 0 and self.noise_channels > 0:
                parts.append(noise.to(x.dtype))
            parts += self._conditioning(k, x.size(0), step_code, batch_dict.get(lk), x)
            h.append(self.node_encoders["fine" if k == 0 else "coarse"](torch.cat(parts, dim=-1)))

        mesh_index, mesh_e, contact_index, contact_e, contact_mask = [], [], [], [], []
        for k in range(num_levels):
            key = edge_type(MESH, k)
            mesh_index.append(edge_index_dict[key])
            mesh_e.append(self.edge_encoders[MESH](edge_attr_dict[key]))
            key = edge_type(CONTACT, k)
            if key in edge_index_dict:
                contact_index.append(edge_index_dict[key])
                contact_e.append(self.edge_encoders[CONTACT](edge_attr_dict[key]))
            else:
                contact_index.append(split_edges(mesh_index[-1])[0].new_empty(2, 0))
                contact_e.append(mesh_e[-1].new_empty(0, self.hidden_channels))
            contact_mask.append(None if contact_mask_dict is None else contact_mask_dict.get(key))

        down_index, down_e, up_index, up_e = [], [], [], []
        for k in range(num_levels - 1):
            for rel, index, e in ((DOWN, down_index, down_e), (UP, up_index, up_e)):
                key = edge_type(rel, k)
                index.append(edge_index_dict[key])
                e.append(self.edge_encoders[rel](edge_attr_dict[key]))

        def intra_stack(stack: nn.ModuleList, k: int) -> None:
            for conv in stack:
                h[k], mesh_e[k], contact_e[k] = conv(
                    h[k], mesh_index[k], mesh_e[k], contact_index[k], contact_e[k], contact_mask[k]
                )

        # ---- V-cycle -----------------------------------------------------------------
        for k in range(num_levels - 1):
            intra_stack(self.pre, k)
            for conv in self.down:
                h[k + 1], down_e[k] = conv((h[k], h[k + 1]), down_index[k], down_e[k])
        coarsest = num_levels - 1
        intra_stack(self.pre, coarsest)
        intra_stack(self.solve, coarsest)
        intra_stack(self.post, coarsest)
        for k in range(num_levels - 2, -1, -1):
            for conv in self.up:
                h[k], up_e[k] = conv((h[k + 1], h[k]), up_index[k], up_e[k])
            intra_stack(self.post, k)

        return self.decoder(h[0])

    def extra_repr(self) -> str:
        """Constructor arguments shown by ``repr``."""
        return (
            f"fine_in_channels={self.fine_in_channels}, coarse_in_channels={self.coarse_in_channels}, "
            f"out_channels={self.out_channels}, hidden_channels={self.hidden_channels}, "
            f"mlp_channels={self.mlp_channels}, noise_channels={self.noise_channels}, "
            f"num_levels={self.num_levels}, aggr={self.aggr!r}"
        )


def _edge_channels(edge_channels: int | Mapping[str, int], relations: tuple[str, ...]) -> dict[str, int]:
    """``{relation: input width}`` from one width for all or a mapping; one-line error for a missing one."""
    if isinstance(edge_channels, int):
        return dict.fromkeys(relations, edge_channels)
    missing = [rel for rel in relations if rel not in edge_channels]
    if missing:
        raise ValueError(f"edge_channels: no width for {missing} (needs {list(relations)})")
    return {rel: int(edge_channels[rel]) for rel in relations}
