"""AMPN: the algebraic-hierarchical message passing network (V-cycle) of the seed paper."""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData
from torch_geometric.nn.aggr import Aggregation

from torch_ampn.hierarchy.hierarchical_data import (
    CONTACT,
    DOWN,
    MESH,
    UP,
    EdgeType,
    check_level_counts,
    edge_type,
    level_name,
)
from torch_ampn.nn._conv import check_aggr
from torch_ampn.nn.encoding import FourierLevelEncoding
from torch_ampn.nn.inter_level_conv import InterLevelConv
from torch_ampn.nn.intra_level_conv import IntraLevelConv
from torch_ampn.nn.normalizer import Normalizer
from torch_ampn.nn.slots import split_edges
from torch_ampn.nn.transfer import restrict_mean

EdgeDict = dict[EdgeType, Tensor]


class AMPN(nn.Module):
    r"""Algebraic-hierarchical message passing network (seed paper, "Processor and decoder").

    A V-cycle of message passing over a graph hierarchy (a :class:`~torch_ampn.hierarchy.HierarchicalData`,
    e.g. from :class:`~torch_ampn.transforms.AMGHierarchy`), mapping ``l0`` node features to
    ``out_channels`` per ``l0`` node.

    **Encoder.** One linear layer per node kind (fine ``l0`` nodes; coarse ``l1 .. lL``
    nodes) and per edge relation (mesh, contact if used, down, up) maps the input features to
    :math:`d` = ``hidden_channels``. The input of a node is its features, followed by the
    :class:`FourierLevelEncoding` of its level and, with ``cond_channels > 0``, a conditioning
    vector (one per graph, or one for all).

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

    **Decoder.** A linear layer on the final ``l0`` embeddings, ``[N_0, out_channels]``.

    **Defaults.** The generic defaults differ from the seed paper's network (``aggr="max"``,
    ``mlp_norm=True``, ``transfer_weights=False``, ``coarse_inputs="none"``)
    where the reach benchmark (``benchmarks/reach/``,
    docs/generic.md) measured a gain: on Laplace's equation on 4,096-node meshes (150 s of
    training on one core) the paper's settings err 2.5 times as much. :class:`RobinAMPN` (the
    forming surrogates) keeps the paper's settings.

    **Flat baseline** (``num_levels=1``): a MeshGraphNet-style processor on ``l0`` only:
    Pre, Solve, Post (``3 + 5 + 3 = 11`` :class:`IntraLevelConv` layers); the Down/Up stacks
    and the coarse-node, down- and up-edge encoders are not created.

    The forward pass is compile-friendly: the level loop is static (``num_levels`` is fixed
    per model), there is no ``.item()`` and no boolean indexing; fixed-size contact tables
    with a validity mask give static shapes. The ROBIN (diffusion) mode is
    :class:`~torch_ampn.nn.RobinAMPN` with :class:`~torch_ampn.nn.DiffusionAMPN`.

    Args:
        in_channels: Node features of ``l0`` (``data["l0"].x``).
        out_channels: Size of the prediction per ``l0`` node.
        edge_channels: Input features of the edges (``edge_attr``): one number for every
            relation, or one per relation ``{"mesh": ..., "contact": ..., "down": ..., "up": ...}``
            (down and up only with ``num_levels > 1``); ``None`` or 0: the edges carry no
            features (:meth:`inputs` gives them a constant 1, ``[E, 1]``: their embedding is learnt).
        hidden_channels: Latent size :math:`d` of node and edge embeddings.
        num_levels: Levels used, ``L + 1`` (paper: 4); ``1`` is the flat baseline. The
            input may hold more levels (the coarser ones are ignored), not fewer.
        pre_layers: Layers of the Pre stack.
        down_layers: Layers of the Down stack.
        solve_layers: Layers of the Solve stack.
        post_layers: Layers of the Post stack.
        up_layers: Layers of the Up stack.
        aggr: Aggregation of all layers: ``"sum"`` (default), ``"max"`` (the paper's), ``"mean"``
            or a ``torch_geometric.nn.aggr.Aggregation`` (each layer gets its own copy, so a
            learnable aggregation is learnt per layer).
        mlp_channels: Hidden width of the layer MLPs (paper: 128, whatever :math:`d` is).
        coarse_in_channels: Node features of coarse levels (``data["lk"].x``, ``k >= 1``);
            0 (default): coarse nodes start from their level encoding only.
        relations: The intra-level edge relations: ``("mesh",)`` or ``("mesh", "contact")``
            (contact edges, e.g. from :class:`~torch_ampn.transforms.ComponentRadiusGraph`).
            Without ``"contact"`` the network has no contact parameters.
        num_level_frequencies: Frequencies of the level encoding (``2 F`` inputs).
        cond_channels: Width of the conditioning vector appended to every node's input
            (:meth:`forward`'s ``cond``); 0: none.
        transfer_weights: Down and Up aggregate by the weighted mean with the prolongator's
            weights (the down and up edges' ``edge_weight`` from
            :func:`~torch_ampn.hierarchy.build_hierarchy`): restriction and interpolation as
            in multigrid, instead of ``aggr`` (see :class:`InterLevelConv`); the default. ``False``:
            ``aggr``, as in the paper.
        coarse_inputs: ``"restrict"`` (default): each coarse node also gets the weighted mean of
            the ``l0`` inputs over its aggregate (restricted level by level with the down edges'
            weights, as multigrid restricts a right-hand side); ``"none"`` (the paper's): coarse
            nodes start from their level encoding (and ``data["lk"].x`` with
            ``coarse_in_channels > 0``).
        normalize: Standardise the ``l0`` inputs (and ``data["lk"].x``) and every edge
            relation's features, per level, with statistics accumulated in training mode over the
            first ``normalize_batches`` batches (then frozen; kept in the state dict), as
            MeshGraphNets' online normalisers do (default ``True``; ``False`` is the paper's).
            Without it, inputs must be scaled by the user (mesh edge features of a fine mesh are
            ``O(h)``, a boundary value on a few nodes is mostly zeros). On the reach benchmark it
            is what makes the plate-elasticity problem learnable (relative L2 0.32 against 1.26
            in 600 s) and it does not hurt Laplace's equation (0.113 against 0.131-0.139).
        normalize_batches: Training batches whose statistics the normalisers accumulate.
        mlp_norm: Whether the layers' MLPs start with a layer normalisation (the paper's; default
            ``False``). Without it, an MLP keeps the scale of its input, so an answer proportional
            to the data (a linear PDE's) is easier to represent.

    Example:
        >>> from torch_ampn.datasets import laplace_sample
        >>> from torch_ampn.transforms import AMGHierarchy
        >>> h = AMGHierarchy(num_levels=3)(laplace_sample(2000, seed=0))  # 2-D: pos [N, 2], x [N, 4]
        >>> model = AMPN(4, 1, edge_channels=3, hidden_channels=32, num_levels=3)  # 3 = 2-D x_i - x_j, norm
        >>> model(h).shape
        torch.Size([2116, 1])
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        edge_channels: int | Mapping[str, int] | None = None,
        hidden_channels: int = 128,
        num_levels: int = 4,
        pre_layers: int = 3,
        down_layers: int = 2,
        solve_layers: int = 5,
        post_layers: int = 3,
        up_layers: int = 2,
        aggr: str | Aggregation = "sum",
        mlp_channels: int = 128,
        coarse_in_channels: int = 0,
        relations: Sequence[str] = (MESH,),
        num_level_frequencies: int = 4,
        cond_channels: int = 0,
        transfer_weights: bool = True,
        coarse_inputs: str = "restrict",
        normalize: bool = True,
        normalize_batches: int = 100,
        mlp_norm: bool = False,
    ) -> None:
        super().__init__()
        if num_levels < 1:
            raise ValueError(f"num_levels must be >= 1, got {num_levels}")
        if num_levels > 1 and (down_layers < 1 or up_layers < 1):
            raise ValueError("a hierarchy (num_levels > 1) needs down_layers >= 1 and up_layers >= 1")
        if coarse_inputs not in ("none", "restrict"):
            raise ValueError(f"coarse_inputs must be 'none' or 'restrict', got {coarse_inputs!r}")
        relations = tuple(relations)
        if relations not in ((MESH,), (MESH, CONTACT)):
            raise ValueError(f"relations must be ('mesh',) or ('mesh', 'contact'), got {relations}")
        self.in_channels = in_channels
        self.coarse_in_channels = coarse_in_channels
        self.out_channels = out_channels
        self.hidden_channels = hidden_channels
        self.num_levels = num_levels
        self.relations = relations
        self.cond_channels = cond_channels
        self.transfer_weights = bool(transfer_weights)
        self.coarse_inputs = coarse_inputs
        self.normalize = bool(normalize)
        self.normalize_batches = int(normalize_batches)
        self.mlp_norm = bool(mlp_norm)
        aggr = check_aggr(aggr)
        self.aggr = aggr if isinstance(aggr, str) else repr(aggr)  # a template module is not registered
        self.mlp_channels = mlp_channels
        contact = CONTACT in relations

        self.level_encoding = FourierLevelEncoding(num_level_frequencies, max_index=8.0)
        cond = self.level_encoding.out_channels + cond_channels
        d, h = hidden_channels, self.mlp_channels
        hierarchical = num_levels > 1

        self.node_encoders = nn.ModuleDict({"fine": nn.Linear(in_channels + cond, d)})
        self.edge_widths = _edge_channels(edge_channels, relations + ((DOWN, UP) if hierarchical else ()))
        # an edge relation without features gets a constant 1 as its input (a learnt embedding)
        width = {rel: max(w, 1) for rel, w in self.edge_widths.items()}
        self.edge_encoders = nn.ModuleDict({rel: nn.Linear(width[rel], d) for rel in relations})
        coarse_width = coarse_in_channels + (in_channels if coarse_inputs == "restrict" else 0)
        if hierarchical:  # (created in this order, which the initialisation's random draws follow)
            self.node_encoders["coarse"] = nn.Linear(coarse_width + cond, d)
            self.edge_encoders[DOWN] = nn.Linear(width[DOWN], d)
            self.edge_encoders[UP] = nn.Linear(width[UP], d)

        def intra(n: int) -> nn.ModuleList:
            return nn.ModuleList(
                IntraLevelConv(d, h, copy.deepcopy(aggr), contact=contact, mlp_norm=mlp_norm)
                for _ in range(n)
            )

        def inter(n: int) -> nn.ModuleList:
            return nn.ModuleList(
                InterLevelConv(d, h, copy.deepcopy(aggr), mlp_norm=mlp_norm) for _ in range(n)
            )

        self.pre = intra(pre_layers)
        self.solve = intra(solve_layers)
        self.post = intra(post_layers)
        self.down = inter(down_layers) if hierarchical else nn.ModuleList()
        self.up = inter(up_layers) if hierarchical else nn.ModuleList()
        self.decoder = nn.Linear(d, out_channels)
        if self.normalize:  # buffers only: no parameter, no random draw
            self.node_norm = nn.ModuleDict({"fine": Normalizer(in_channels)})
            if hierarchical and coarse_in_channels > 0:
                self.node_norm["coarse"] = Normalizer(coarse_in_channels)
            self.edge_norm = nn.ModuleDict(
                {
                    f"{rel}{k}": Normalizer(max(width, 1))
                    for rel, width in self.edge_widths.items()
                    for k in range(num_levels)
                }
            )
            self.register_buffer("normalized_batches", torch.zeros((), dtype=torch.long))
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
        self, level: int, num_nodes: int, cond: Tensor | None, batch: Tensor | None, like: Tensor
    ) -> list[Tensor]:
        """Level encoding (and conditioning) of ``num_nodes`` nodes of ``level``: list of ``[N, *]``."""
        out = [self.level_encoding(level).to(like.dtype).expand(num_nodes, -1)]  # [N, 2F]
        if cond is not None:
            if cond.dim() == 2 and cond.size(0) > 1:  # [B, C]: one per graph
                if batch is None:
                    raise ValueError("a conditioning vector per graph ([B, C]) needs batch_dict")
                code = cond[batch]
            else:  # [C] or [1, C]: the same everywhere
                code = cond.reshape(1, -1).expand(num_nodes, -1)
            out.append(code.to(like.dtype))
        return out

    def inputs(
        self, data: HeteroData
    ) -> tuple[dict[str, Tensor], EdgeDict, EdgeDict, dict[str, Tensor] | None, EdgeDict]:
        """``(x_dict, edge_index_dict, edge_attr_dict, batch_dict, edge_weight_dict)`` of a hierarchy.

        Reads ``data["l0"].x``, ``data["lk"].x`` (with ``coarse_in_channels > 0``) and every
        used relation's ``edge_index`` and ``edge_attr`` (a relation of width 0 needs no
        ``edge_attr`` and gets ones ``[E, 1]``; a missing contact relation counts as empty), and
        the down and up edges' ``edge_weight`` where present (needed with ``transfer_weights``
        or ``coarse_inputs="restrict"``).
        """
        num_levels = self.num_levels
        if len(data.node_types) < num_levels:
            levels = len(data.node_types)
            raise ValueError(f"AMPN with num_levels={num_levels}: the data has {levels} level(s)")
        check_level_counts(data, num_levels)  # a batch of hierarchies: every graph has the levels
        fine = data[level_name(0)]
        if "x" not in fine:
            raise ValueError("AMPN: the data has no node features data['l0'].x")
        x = fine.x
        if x.dim() != 2 or x.size(1) != self.in_channels:
            raise ValueError(f"AMPN: data['l0'].x must be [N, {self.in_channels}], got {list(x.shape)}")
        x_dict = {level_name(0): x}
        for k in range(1, num_levels):
            store = data[level_name(k)]
            if self.coarse_in_channels > 0:
                if "x" not in store:
                    raise ValueError(f"AMPN(coarse_in_channels={self.coarse_in_channels}): no data['l{k}'].x")
                x_dict[level_name(k)] = store.x
            else:
                x_dict[level_name(k)] = x.new_empty(store.num_nodes, 0)
        edge_index_dict, edge_attr_dict, edge_weight_dict = {}, {}, {}
        keys = [(rel, k) for k in range(num_levels) for rel in self.relations]
        keys += [(rel, k) for k in range(num_levels - 1) for rel in (DOWN, UP)]
        for rel, k in keys:
            key = edge_type(rel, k)
            if key not in data.edge_types:
                if rel == CONTACT:
                    continue
                raise ValueError(f"AMPN: the data has no {key} edges")
            store = data[key]
            edge_index_dict[key] = store.edge_index
            if rel in (DOWN, UP) and "edge_weight" in store:
                edge_weight_dict[key] = store.edge_weight
            width = self.edge_widths[rel]
            if width == 0:
                edge_attr_dict[key] = x.new_ones(store.edge_index.size(1), 1)
            elif "edge_attr" not in store or store.edge_attr.size(-1) != width:
                got = list(store.edge_attr.shape) if "edge_attr" in store else None
                raise ValueError(f"AMPN: data[{key}].edge_attr must be [E, {width}], got {got}")
            else:
                edge_attr_dict[key] = store.edge_attr
        batched = "batch" in fine
        batch_dict = None
        if batched:
            batch_dict = {level_name(k): data[level_name(k)].batch for k in range(num_levels)}
        return x_dict, edge_index_dict, edge_attr_dict, batch_dict, edge_weight_dict

    def forward(
        self,
        x_dict: dict[str, Tensor] | HeteroData,
        edge_index_dict: dict[EdgeType, Tensor] | None = None,
        edge_attr_dict: dict[EdgeType, Tensor] | None = None,
        batch_dict: dict[str, Tensor] | None = None,
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
        cond: Tensor | None = None,
        edge_weight_dict: dict[EdgeType, Tensor] | None = None,
    ) -> Tensor:
        """The prediction of every ``l0`` node, ``[N_0, out_channels]``.

        Either ``model(data)`` on a (batched) :class:`~torch_ampn.hierarchy.HierarchicalData`
        (see :meth:`inputs`), or the dict form keyed like one, which the forming surrogate uses.

        Args:
            x_dict: The hierarchy, or node features ``{"lk": [N_k, F_k]}`` for ``k < num_levels``
                (``in_channels`` for ``l0``, ``coarse_in_channels`` otherwise).
            edge_index_dict: ``{(src, rel, dst): LongTensor[2, E]}`` rows ``(source, target)``:
                ``("lk", "mesh", "lk")`` (and ``("lk", "contact", "lk")``: a missing contact set
                counts as empty) for every used level, ``("lk", "down", "lk+1")`` and
                ``("lk+1", "up", "lk")`` between used levels. Other keys are ignored. Any
                of them may be a :class:`~torch_ampn.nn.SlottedEdgeIndex` (the edges with
                their aggregation table; what :class:`~torch_ampn.rollout.fast.FastRollout`
                passes): those aggregate by a dense reduction (same result).
            edge_attr_dict: Edge features with the same keys, ``[E, edge width]``.
            batch_dict: ``{"lk": LongTensor[N_k]}`` graph of every node; needed only for a
                per-graph ``cond``.
            contact_mask_dict: Optional ``{("lk", "contact", "lk"): BoolTensor[M_k]}``
                validity masks of fixed-size contact tables (see :class:`IntraLevelConv`).
            cond: Conditioning ``[cond_channels]`` (every node) or ``[B, cond_channels]`` (per graph).
            edge_weight_dict: ``{("lk", "down", "lk+1"): [E], ("lk+1", "up", "lk"): [E]}`` the
                prolongator's weights; needed with ``transfer_weights`` or
                ``coarse_inputs="restrict"`` (a hierarchy passed whole brings its own).

        Returns:
            ``[N_0, out_channels]``.
        """
        if isinstance(x_dict, HeteroData):
            x_dict, edge_index_dict, edge_attr_dict, found, weights = self.inputs(x_dict)
            batch_dict = batch_dict if batch_dict is not None else found
            edge_weight_dict = edge_weight_dict if edge_weight_dict is not None else weights
        if edge_index_dict is None or edge_attr_dict is None:
            raise ValueError("AMPN: pass a HierarchicalData, or x_dict, edge_index_dict and edge_attr_dict")
        num_levels = self.num_levels
        names = [level_name(k) for k in range(num_levels)]
        for lk in names:
            if lk not in x_dict:
                raise KeyError(f"AMPN with num_levels={num_levels} needs node features for {lk!r}")
        if (cond is None) != (self.cond_channels == 0):
            raise ValueError(f"AMPN(cond_channels={self.cond_channels}): pass `cond` exactly when it is > 0")
        batch_dict = batch_dict or {}
        contact = CONTACT in self.relations
        weights = self._transfer_weights(edge_weight_dict)
        if self.normalize:
            x_dict, edge_attr_dict = self._normalized(x_dict, edge_attr_dict)

        # ---- encode ------------------------------------------------------------------
        h: list[Tensor] = []  # node embeddings per level, [N_k, d]
        restricted = x_dict[names[0]]  # [N_k, F]: the l0 inputs restricted to level k
        for k, lk in enumerate(names):
            x = x_dict[lk]
            if k > 0 and self.coarse_inputs == "restrict":
                down = edge_index_dict[edge_type(DOWN, k - 1)]
                restricted = restrict_mean(
                    restricted, restricted.new_ones(restricted.size(0)), down, weights[DOWN][k - 1], x.size(0)
                )[0]  # [N_k, F]
                x = torch.cat([x, restricted], dim=-1)
            parts = [x, *self._conditioning(k, x.size(0), cond, batch_dict.get(lk), x)]
            h.append(self.node_encoders["fine" if k == 0 else "coarse"](torch.cat(parts, dim=-1)))

        mesh_index, mesh_e = [], []
        contact_index: list[Tensor | None] = []
        contact_e: list[Tensor | None] = []
        contact_mask: list[Tensor | None] = []
        for k in range(num_levels):
            key = edge_type(MESH, k)
            mesh_index.append(edge_index_dict[key])
            mesh_e.append(self.edge_encoders[MESH](edge_attr_dict[key]))
            key = edge_type(CONTACT, k)
            if not contact:
                contact_index.append(None)
                contact_e.append(None)
            elif key in edge_index_dict:
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
        transfer = self.transfer_weights
        for k in range(num_levels - 1):
            intra_stack(self.pre, k)
            for conv in self.down:
                w = weights[DOWN][k] if transfer else None
                h[k + 1], down_e[k] = conv((h[k], h[k + 1]), down_index[k], down_e[k], w)
        coarsest = num_levels - 1
        intra_stack(self.pre, coarsest)
        intra_stack(self.solve, coarsest)
        intra_stack(self.post, coarsest)
        for k in range(num_levels - 2, -1, -1):
            for conv in self.up:
                w = weights[UP][k] if transfer else None
                h[k], up_e[k] = conv((h[k + 1], h[k]), up_index[k], up_e[k], w)
            intra_stack(self.post, k)

        return self.decoder(h[0])

    def _transfer_weights(self, edge_weight_dict: dict[EdgeType, Tensor] | None) -> dict[str, list[Tensor]]:
        """``{"down": [w_0, ..], "up": [..]}`` per level pair where the options need them, else empty."""
        out: dict[str, list[Tensor]] = {DOWN: [], UP: []}
        if self.num_levels == 1 or not (self.transfer_weights or self.coarse_inputs == "restrict"):
            return out
        for rel in (DOWN, UP):
            for k in range(self.num_levels - 1):
                key = edge_type(rel, k)
                if edge_weight_dict is None or key not in edge_weight_dict:
                    raise ValueError(
                        f"AMPN(transfer_weights={self.transfer_weights}, "
                        f"coarse_inputs={self.coarse_inputs!r}) needs the prolongator weights "
                        f"data[{key}].edge_weight (AMGHierarchy stores them)"
                    )
                out[rel].append(edge_weight_dict[key])
        return out

    def _normalized(
        self, x_dict: dict[str, Tensor], edge_attr_dict: dict[EdgeType, Tensor]
    ) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
        """Inputs standardised by the online normalisers (updated first while training, until frozen)."""
        update = self.training and torch.is_grad_enabled()
        update = update and int(self.normalized_batches) < self.normalize_batches
        if update:
            self.normalized_batches += 1

        def apply(norm: Normalizer, value: Tensor) -> Tensor:
            if update:
                norm.update(value)
            return norm(value)

        nodes = dict(x_dict)  # new dicts: the caller's stay as they were
        for k in range(self.num_levels):
            kind = "fine" if k == 0 else "coarse"
            if kind in self.node_norm:
                nodes[level_name(k)] = apply(self.node_norm[kind], x_dict[level_name(k)])
        edges = dict(edge_attr_dict)
        for key, attr in edge_attr_dict.items():
            name = f"{key[1]}{key[0][1:] if key[1] != UP else key[2][1:]}"  # relation and its fine level
            if name in self.edge_norm:
                edges[key] = apply(self.edge_norm[name], attr)
        return nodes, edges

    def extra_repr(self) -> str:
        """Constructor arguments shown by ``repr``."""
        return (
            f"in_channels={self.in_channels}, coarse_in_channels={self.coarse_in_channels}, "
            f"out_channels={self.out_channels}, hidden_channels={self.hidden_channels}, "
            f"mlp_channels={self.mlp_channels}, num_levels={self.num_levels}, "
            f"relations={self.relations}, aggr={self.aggr!r}"
            + (", transfer_weights=True" if self.transfer_weights else "")
            + (f", coarse_inputs={self.coarse_inputs!r}" if self.coarse_inputs != "none" else "")
            + (", normalize=True" if self.normalize else "")
            + ("" if self.mlp_norm else ", mlp_norm=False")
        )


def _edge_channels(
    edge_channels: int | Mapping[str, int] | None, relations: tuple[str, ...]
) -> dict[str, int]:
    """``{relation: input width}`` from one width for all or a mapping; one-line error for a missing one."""
    if edge_channels is None:
        return dict.fromkeys(relations, 0)
    if isinstance(edge_channels, int):
        return dict.fromkeys(relations, edge_channels)
    missing = [rel for rel in relations if rel not in edge_channels]
    if missing:
        raise ValueError(f"edge_channels: no width for {missing} (needs {list(relations)})")
    return {rel: int(edge_channels[rel]) for rel in relations}
