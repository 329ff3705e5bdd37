r"""Input features of an AMPN (seed paper, "Feature and encoder"), from plain tensors or a hierarchy.

Every function works on batched graphs: node tensors are concatenated over the graphs of a
batch and graph-level tensors (gripper positions and forces, ``[B, G, 3]``) are picked per
node with the node-level ``batch`` vector.

Feature layout (columns, in this order):

* fine (``l0``) nodes, :func:`fine_node_features`: node-type one-hot (``NodeType.count()``),
  previous residual :math:`\Delta u^{t-1}` (3), prescribed tool motion
  :math:`\Delta u^t_{BC}` (3, zero on plies), fiber direction (3: a unit vector in the
  initial configuration, zero on tools), the component encoding (:func:`component_features`:
  a one-hot of ``num_components`` columns, or the ply's place in its stack), and the
  gripper features of :func:`gripper_features` (``7 G + 7``); for models with prior features,
  :func:`prior_features` (6) last. The N(0, 1) noise input (the
  noisy target in ROBIN mode) is *not* part of these columns: :class:`~torch_ampn.nn.RobinAMPN`
  takes it as its own argument and appends it, so that a denoiser can change it per step.
* coarse (``l1 .. lL``) nodes, :func:`coarse_node_features`: node-type one-hot only.
* edges, :func:`edge_features`: :math:`x_i - x_j` (3) and its norm (1) on every edge set,
  plus :math:`x^0_i - x^0_j` (3) and its norm (1) on mesh, down and up edges; ``i`` is the
  target and ``j`` the source of the edge.

The level encoding is added inside the model, and normalisation is a separate step
(:class:`~torch_ampn.forming.Normalizer`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.hierarchy.features import edge_features
from torch_ampn.hierarchy.hierarchical_data import (
    CONTACT,
    DOWN,
    MESH,
    RELATIONS,
    UP,
    EdgeType,
    HierarchicalData,
    edge_type,
    level_name,
)

#: Gripper features per node and gripper: d_ij (3), |d_ij| (1), d_ij / (|d_ij| + eps) (3).
GRIPPER_FEATURES_PER_GRIPPER = 7
#: Gripper features per node summed over grippers: f^proj-weighted (3), f^weighted (3), |f^weighted| (1).
GRIPPER_FEATURES_SUMMED = 7
#: Edge features without (contact) and with (mesh, down, up) the initial relative position.
EDGE_FEATURES_CURRENT = 4
EDGE_FEATURES_WITH_INITIAL = 8
#: Edge relations that carry the initial relative position.
RELATIONS_WITH_INITIAL = (MESH, DOWN, UP)


#: Columns of :func:`prior_features`: the offset from the prior and the prior's next step.
PRIOR_FEATURES = 6

#: Ways to tell a node's component (:func:`component_features`).
COMPONENT_ENCODINGS = ("onehot", "stack")
#: Columns of the ``"stack"`` component encoding: plies below and above a ply node.
STACK_FEATURES = 2


def num_component_features(num_components: int, encoding: str = "onehot") -> int:
    """Columns of :func:`component_features`."""
    _check_encoding(encoding)
    return num_components if encoding == "onehot" else STACK_FEATURES


def num_fine_node_features(
    num_components: int,
    num_grippers: int,
    fiber_channels: int = 3,
    component_encoding: str = "onehot",
    prior: bool = False,
    bundle_steps: int = 1,
) -> int:
    """Number of columns of :func:`fine_node_features` (without the noise input).

    ``bundle_steps`` ``B``: the prescribed tool motion has ``3 B`` columns (its offsets over
    the ``B`` steps a bundled model predicts at once).
    """
    return (
        (PRIOR_FEATURES if prior else 0)
        + NodeType.count()
        + 3  # previous residual
        + 3 * bundle_steps  # prescribed tool motion
        + fiber_channels
        + num_component_features(num_components, component_encoding)
        + GRIPPER_FEATURES_PER_GRIPPER * num_grippers
        + GRIPPER_FEATURES_SUMMED
    )


def _check_encoding(encoding: str) -> None:
    if encoding not in COMPONENT_ENCODINGS:
        raise ValueError(f"component_encoding must be one of {COMPONENT_ENCODINGS}, got {encoding!r}")


def component_features(
    component: Tensor,
    node_type: Tensor,
    num_components: int,
    encoding: str = "onehot",
    batch: Tensor | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """How a node's component enters its features, ``[N, num_component_features(C, encoding)]``.

    * ``"onehot"`` (the paper's): a one-hot of the component id. It ties the features to one
      numbering of one part's components (a 6-ply stack would need more columns, and the
      punch of a 4-ply part would look like the fifth ply of a 6-ply one).
    * ``"stack"``: what a component *is*, the same on every part: for a ply node, the number of
      plies below and above its ply in its graph's stack (ply components are numbered from
      the bottom, ``0 .. P - 1``, as the embedded simulator and ``torch-ampn-data convert``
      number them); zeros on tools, whose kind the node-type one-hot tells. Independent of the
      number of components and of how the tools are numbered.

    Args:
        component: Component id ``LongTensor[N]``.
        node_type: :class:`~torch_ampn.data.NodeType` of every node.
        num_components: ``C`` (width of the one-hot).
        encoding: ``"onehot"`` or ``"stack"``.
        batch: Graph of every node (``"stack"`` counts each graph's plies); ``None``: one graph.
        dtype: Output dtype.
    """
    _check_encoding(encoding)
    if encoding == "onehot":
        return F.one_hot(component.long(), num_components).to(dtype)
    ply = torch.eq(node_type, int(NodeType.PLY))  # [N] (a plain int: traceable by torch.compile)
    graph = batch if batch is not None else torch.zeros_like(component)
    # one slot per node holds every graph id (a static size: no sync, compiles as it is)
    top = torch.full((max(graph.numel(), 1),), -1, dtype=torch.long, device=component.device)
    top = top.scatter_reduce(0, graph, torch.where(ply, component.long(), -1), "amax")  # [B] top ply id
    below = component.long()
    above = top[graph] - below
    stack = torch.stack([below, above], dim=-1).to(dtype)  # [N, 2]
    return torch.where(ply[:, None], stack, 0.0)


def num_coarse_node_features() -> int:
    """Number of columns of :func:`coarse_node_features`."""
    return NodeType.count()


def num_edge_features(relation: str) -> int:
    """Number of columns of :func:`edge_features` for an edge relation (``"mesh"``, ``"contact"``, ...)."""
    return EDGE_FEATURES_WITH_INITIAL if relation in RELATIONS_WITH_INITIAL else EDGE_FEATURES_CURRENT


def node_type_one_hot(node_type: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """One-hot node type: ``LongTensor[N] -> [N, NodeType.count()]``."""
    return F.one_hot(node_type.long(), NodeType.count()).to(dtype)


def _per_node(graph_tensor: Tensor, batch: Tensor | None, num_nodes: int) -> Tensor:
    """``[G, 3]`` or ``[B, G, 3]`` graph-level tensor -> ``[N, G, 3]`` (row ``batch[i]`` for node ``i``)."""
    if graph_tensor.dim() == 2:
        graph_tensor = graph_tensor.unsqueeze(0)  # [1, G, 3]
    if batch is None:
        if graph_tensor.size(0) != 1:
            raise ValueError(
                f"gripper tensors hold {graph_tensor.size(0)} graphs; pass the node `batch` vector"
            )
        return graph_tensor.expand(num_nodes, -1, -1)
    return graph_tensor[batch]


def gripper_features(
    pos: Tensor,
    gripper_pos: Tensor,
    gripper_force: Tensor,
    batch: Tensor | None = None,
    alpha: float = 3e-2,
    eps: float = 1e-8,
) -> Tensor:
    r"""Gripper features of every node (seed paper, "Feature and encoder").

    For node position :math:`\mathbf{x}_i`, gripper positions :math:`\mathbf{g}_j` and
    forces :math:`\mathbf{f}_j`: :math:`\mathbf{d}_{ij} = \mathbf{x}_i - \mathbf{g}_j`,
    :math:`d_{ij} = \|\mathbf{d}_{ij}\|`,
    :math:`\hat{\mathbf{d}}_{ij} = \mathbf{d}_{ij} / (d_{ij} + \epsilon)`,

    .. math::
        \mathbf{f}^{proj}_i = \sum_j \frac{(\mathbf{f}_j \cdot \hat{\mathbf{d}}_{ij})\,
        \hat{\mathbf{d}}_{ij}}{\exp(\alpha d_{ij} + \epsilon)}, \qquad
        \mathbf{f}^{w}_i = \sum_j \frac{\mathbf{f}_j}{\exp(\alpha d_{ij} + \epsilon)}.

    Args:
        pos: Current node positions ``[N, 3]``.
        gripper_pos: Gripper positions ``[G, 3]`` (one graph) or ``[B, G, 3]``.
        gripper_force: Gripper force vectors, same shape as ``gripper_pos``.
        batch: Graph of every node ``LongTensor[N]`` (needed when ``B > 1``).
        alpha: Decay rate :math:`\alpha` of the distance weighting (per length unit).
        eps: :math:`\epsilon`.

    Returns:
        ``[N, 7 G + 7]``: per gripper ``j`` (gripper-major) the columns
        :math:`[\mathbf{d}_{ij}, d_{ij}, \hat{\mathbf{d}}_{ij}]`, then
        :math:`[\mathbf{f}^{proj}_i, \mathbf{f}^{w}_i, \|\mathbf{f}^{w}_i\|]`.
    """
    n = pos.size(0)
    g = _per_node(gripper_pos.to(pos.dtype), batch, n)  # [N, G, 3]
    f = _per_node(gripper_force.to(pos.dtype), batch, n)  # [N, G, 3]
    d = pos.unsqueeze(1) - g  # [N, G, 3]
    dist = d.norm(dim=-1, keepdim=True)  # [N, G, 1]
    d_hat = d / (dist + eps)  # [N, G, 3]
    weight = torch.exp(-(alpha * dist + eps))  # [N, G, 1] = 1 / exp(alpha d + eps)
    f_proj = ((f * d_hat).sum(-1, keepdim=True) * d_hat * weight).sum(1)  # [N, 3]
    f_weighted = (f * weight).sum(1)  # [N, 3]
    per_gripper = torch.cat([d, dist, d_hat], dim=-1).reshape(n, -1)  # [N, 7G]
    return torch.cat([per_gripper, f_proj, f_weighted, f_weighted.norm(dim=-1, keepdim=True)], dim=-1)


def prior_features(pos: Tensor, prior_pos: Tensor, prior_next: Tensor) -> Tensor:
    r"""Where a prior prediction of the trajectory puts every node, relative to the node, ``[N, 6]``.

    A prior :math:`p` (e.g. the POD + GP baseline's trajectory for these settings,
    :mod:`torch_ampn.baselines.prior`) enters as two displacements, invariant to translation:
    the offset :math:`p^{t-1}_i - x^{t-1}_i` of the prior from the current position (3) and the
    prior's step :math:`p^t_i - p^{t-1}_i` (3). A model then learns a correction of the prior
    rather than the whole motion.

    Args:
        pos: Current positions :math:`x^{t-1}` ``[N, 3]``.
        prior_pos: The prior's positions :math:`p^{t-1}` ``[N, 3]``.
        prior_next: The prior's positions :math:`p^t` ``[N, 3]``.
    """
    prior_pos, prior_next = prior_pos.to(pos.dtype), prior_next.to(pos.dtype)
    return torch.cat([prior_pos - pos, prior_next - prior_pos], dim=-1)


def fine_node_features(
    node_type: Tensor,
    prev_disp: Tensor,
    bc_disp: Tensor,
    fiber: Tensor,
    component: Tensor,
    num_components: int,
    gripper: Tensor,
    component_encoding: str = "onehot",
    batch: Tensor | None = None,
    prior: Tensor | None = None,
) -> Tensor:
    r"""Features of the fine (``l0``) nodes, without the noise input.

    Args:
        node_type: :class:`~torch_ampn.data.NodeType` of every node, ``LongTensor[N]``.
        prev_disp: Previous residual :math:`\Delta u^{t-1}`, ``[N, 3]``.
        bc_disp: Prescribed tool motion :math:`\Delta u^t_{BC}` of this step, ``[N, 3]`` (zero on plies;
            ``[N, 3 B]`` for a model that predicts ``B`` steps at once).
        fiber: Fiber direction ``[N, 3]`` (unit vector, zero on tools); any width ``[N, F]`` is accepted.
        component: Component id ``LongTensor[N]`` in ``0 .. num_components - 1``.
        num_components: Number of components ``C`` (width of the component one-hot).
        gripper: The nodes' :func:`gripper_features` ``[N, 7 G + 7]``; its dtype is the output's.
        component_encoding: See :func:`component_features`.
        batch: Graph of every node (for the ``"stack"`` encoding of a batch).
        prior: The nodes' :func:`prior_features` ``[N, 6]``, or ``None`` (a model without them).

    Returns:
        ``[N, num_fine_node_features(C, G, F, component_encoding, prior is not None)]`` in the
        column order of the module docstring.
    """
    dtype = gripper.dtype
    parts = [
        node_type_one_hot(node_type, dtype),
        prev_disp.to(dtype),
        bc_disp.to(dtype),
        fiber.to(dtype),
        component_features(component, node_type, num_components, component_encoding, batch, dtype),
        gripper,
    ]
    if prior is not None:
        parts.append(prior.to(dtype))
    return torch.cat(parts, dim=-1)


def coarse_node_features(node_type: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """Features of coarse (``l1 .. lL``) nodes: the node-type one-hot, ``[N_l, NodeType.count()]``."""
    return node_type_one_hot(node_type, dtype)


def step_features(
    pos: Tensor,
    pos0: Tensor,
    prev_disp: Tensor,
    bc_disp: Tensor,
    node_type: Tensor,
    component: Tensor,
    fiber: Tensor,
    gripper_pos: Tensor,
    gripper_force: Tensor,
    fine_index: Sequence[Tensor],
    edge_index_dict: Mapping[EdgeType, Tensor],
    num_components: int,
    *,
    batch: Tensor | None = None,
    alpha: float = 3e-2,
    eps: float = 1e-8,
    component_encoding: str = "onehot",
    prior: Tensor | None = None,
) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
    r"""All node and edge features of one step from plain tensors (the one feature step of every path).

    The plain path reads these tensors from a window (:func:`hierarchical_features`); the
    fast rollout (:class:`~torch_ampn.rollout.fast.FastRollout`) passes its fixed-shape ones,
    with every slot of a contact table as an edge (invalid slots are masked later by the
    network). Coarse node ``j`` of level ``k`` takes position and node type from the fine node
    ``fine_index[k - 1][j]``.

    Args:
        pos: Positions :math:`x^{t-1}` of the fine nodes ``[N, 3]``.
        pos0: Initial positions ``[N, 3]``.
        prev_disp: Previous residual :math:`\Delta u^{t-1}` ``[N, 3]``.
        bc_disp: Prescribed tool motion of this step ``[N, 3]`` (zero on plies).
        node_type: ``LongTensor[N]``.
        component: ``LongTensor[N]``.
        fiber: Fiber direction ``[N, 3]``.
        gripper_pos: Gripping points ``[G, 3]`` or ``[B, G, 3]`` (:func:`~torch_ampn.data.gripper_points`).
        gripper_force: Gripper forces, same shape (:func:`~torch_ampn.data.gripper_forces`).
        fine_index: For levels ``1 .. L - 1``, the fine node of each coarse node ``LongTensor[N_k]``
            (``L - 1`` tensors: the levels used).
        edge_index_dict: Edge indices keyed like :attr:`HierarchicalData.edge_index_dict`; a
            missing contact edge set counts as empty.
        num_components: ``C``.
        batch: Graph of every fine node (for a batch of ``B`` graphs).
        alpha: See :func:`gripper_features`.
        eps: See :func:`gripper_features`.
        component_encoding: See :func:`component_features`.
        prior: :func:`prior_features` of the fine nodes ``[N, 6]``, or ``None``.

    Returns:
        ``(x_dict, edge_attr_dict)`` as :func:`hierarchical_features`.
    """
    num_levels = len(fine_index) + 1
    grip = gripper_features(pos, gripper_pos, gripper_force, batch, alpha, eps)
    x_dict = {
        "l0": fine_node_features(
            node_type,
            prev_disp,
            bc_disp,
            fiber,
            component,
            num_components,
            grip,
            component_encoding,
            batch,
            prior,
        )
    }
    pos_l, pos0_l = [pos], [pos0]
    for k, idx in enumerate(fine_index, start=1):
        pos_l.append(pos[idx])  # [N_k, 3]
        pos0_l.append(pos0[idx])
        x_dict[level_name(k)] = coarse_node_features(node_type[idx], pos.dtype)
    empty = torch.empty(2, 0, dtype=torch.long, device=pos.device)
    edge_attr_dict: dict[EdgeType, Tensor] = {}
    for k in range(num_levels):
        key = edge_type(MESH, k)
        edge_attr_dict[key] = edge_features(edge_index_dict[key], pos_l[k], pos_l[k], pos0_l[k], pos0_l[k])
        key = edge_type(CONTACT, k)
        edge_attr_dict[key] = edge_features(edge_index_dict.get(key, empty), pos_l[k], pos_l[k])
        if k + 1 < num_levels:
            for rel, src, dst in ((DOWN, k, k + 1), (UP, k + 1, k)):
                key = edge_type(rel, k)
                edge_attr_dict[key] = edge_features(
                    edge_index_dict[key], pos_l[src], pos_l[dst], pos0_l[src], pos0_l[dst]
                )
    return x_dict, edge_attr_dict


def hierarchical_features(
    data: HierarchicalData,
    num_components: int,
    num_levels: int | None = None,
    alpha: float = 3e-2,
    eps: float = 1e-8,
    component_encoding: str = "onehot",
    prior: bool = False,
) -> tuple[dict[str, Tensor], dict[EdgeType, Tensor]]:
    """All node and edge features of a (batched) :class:`~torch_ampn.data.HierarchicalData`.

    Reads ``data["l0"]``'s ``pos0``, ``pos``, ``prev_disp``, ``bc_disp``, ``node_type``,
    ``component``, ``fiber`` (and ``batch`` when batched) and the graph-level
    ``data.gripper_pos`` / ``data.gripper_force`` (``[B, G, 3]``; ``[1, G, 3]`` per graph
    batches to that), and computes them with :func:`step_features`. Coarse nodes take
    position and node type from their root fine node (``data.fine_index(k)``). A missing
    contact edge set counts as empty.

    Args:
        data: The hierarchy (or a batch of hierarchies).
        num_components: Width of the component one-hot.
        num_levels: Use levels ``0 .. num_levels - 1`` only (default: all).
        alpha: See :func:`gripper_features`.
        eps: See :func:`gripper_features`.
        component_encoding: See :func:`component_features`.
        prior: Append :func:`prior_features` to the fine features (reads ``data["l0"]``'s
            ``prior_pos`` and ``prior_next``, which :func:`~torch_ampn.data.step_sample` sets
            from :attr:`~torch_ampn.data.Trajectory.prior`).

    Returns:
        ``(x_dict, edge_attr_dict)``: ``x_dict["lk"]`` node features and
        ``edge_attr_dict[(src, rel, dst)]`` edge features of every edge set of the used
        levels, keyed like ``data.edge_index_dict``; ready for :class:`~torch_ampn.nn.AMPN`
        after normalisation.
    """
    num_levels = data.num_levels if num_levels is None else num_levels
    fine = data["l0"]
    prior_columns = None
    if prior:
        if "prior_pos" not in fine or "prior_next" not in fine:
            raise ValueError(
                "the model takes prior features but the data has no prior (l0.prior_pos / prior_next): "
                "set the trajectories' prior (AMPNDataModule's data.prior)"
            )
        prior_columns = prior_features(fine.pos, fine.prior_pos, fine.prior_next)
    return step_features(
        fine.pos,
        fine.pos0,
        fine.prev_disp,
        fine.bc_disp,
        fine.node_type,
        fine.component,
        fine.fiber,
        data.gripper_pos,
        data.gripper_force,
        [data.fine_index(k) for k in range(1, num_levels)],
        {key: data[key].edge_index for key in data.edge_types},
        num_components,
        batch=fine.batch if "batch" in fine else None,
        alpha=alpha,
        eps=eps,
        component_encoding=component_encoding,
        prior=prior_columns,
    )


def ampn_channels(
    num_components: int,
    num_grippers: int,
    component_encoding: str = "onehot",
    prior: bool = False,
    bundle_steps: int = 1,
) -> dict[str, Any]:
    """The input sizes of a :class:`~torch_ampn.nn.RobinAMPN` for these features: ``RobinAMPN(**sizes)``.

    Returns:
        ``{"fine_in_channels": ..., "coarse_in_channels": ..., "edge_channels": {relation: ...}}``.
    """
    return {
        "fine_in_channels": num_fine_node_features(
            num_components,
            num_grippers,
            component_encoding=component_encoding,
            prior=prior,
            bundle_steps=bundle_steps,
        ),
        "coarse_in_channels": num_coarse_node_features(),
        "edge_channels": {rel: num_edge_features(rel) for rel in RELATIONS},
    }
