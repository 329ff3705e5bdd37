"""Small helpers shared by the tests, in the spirit of ``torch_geometric.testing``.

Devices, brute-force reference graphs, float64 references of the network's building blocks,
random inputs for the message-passing layers, a toy hierarchy with every feature a model needs,
a small trajectory without a simulator and a small simulator setting.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from torch_ampn.data import (
    HierarchicalData,
    NodeType,
    Trajectory,
    build_hierarchy,
    level_name,
    rectangle_mesh,
    stacked_plates,
)

if TYPE_CHECKING:
    from torch_ampn.nn import LayerNormMLP

#: Devices to parametrise tests over: the CPU and, if present, CUDA.
DEVICES: list[str] = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])

#: A small stamp-forming setting for tests (plies of 5 x 5 x 2 triangles, 4 x 4 tool quads, 6 saved
#: steps), as the overrides of :class:`~torch_ampn.sim.StampFormingConfig` that a YAML file or
#: ``data.simulator`` gives (lists, not tuples). ``StampFormingConfig.from_dict(SMALL_SIMULATOR)``
#: is the setting itself.
SMALL_SIMULATOR: dict[str, Any] = {"ply_cells": 5, "punch_cells": [4, 4], "die_cells": [4, 4], "num_steps": 6}

#: :data:`SMALL_SIMULATOR` for a quarter of the stroke in a quarter of the time: the punch at the
#: same speed, a quarter of the solver's substeps. For tests of bookkeeping (files, settings,
#: repeat runs), not of the forming.
QUICK_SIMULATOR: dict[str, Any] = {**SMALL_SIMULATOR, "duration": 0.25, "stroke": 15.0}


def count_parameters(module: nn.Module) -> int:
    """Number of scalar learnable parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def random_edge_index(
    num_src: int, num_dst: int, num_edges: int, generator: torch.Generator | None = None
) -> Tensor:
    """Random ``LongTensor[2, E]`` with sources in ``[0, num_src)`` and targets in ``[0, num_dst)``."""
    src = torch.randint(0, num_src, (num_edges,), generator=generator)
    dst = torch.randint(0, num_dst, (num_edges,), generator=generator)
    return torch.stack([src, dst])


def random_intra_level_inputs(
    num_nodes: int,
    num_mesh_edges: int,
    num_contact_edges: int,
    channels: int,
    seed: int = 0,
    mask_drop_prob: float | None = None,
) -> tuple[Tensor, ...]:
    """Random arguments of :class:`~torch_ampn.nn.IntraLevelConv`, drawn from one seeded generator.

    Args:
        num_nodes: Number of nodes ``N``.
        num_mesh_edges: Number of mesh edges ``E_m`` (random pairs, may repeat).
        num_contact_edges: Number of contact edges ``E_c`` (random pairs, may repeat).
        channels: Feature size ``d`` of nodes and edges.
        seed: Seed of the generator all tensors are drawn from, in the order returned.
        mask_drop_prob: If given, a contact mask ``[E_c]`` is appended that drops each contact
            edge with this probability.

    Returns:
        ``(x [N, d], mesh_index [2, E_m], e_mesh [E_m, d], contact_index [2, E_c],
        e_contact [E_c, d])``, then ``contact_mask [E_c]`` (bool) if ``mask_drop_prob`` is given.
    """
    g = torch.Generator().manual_seed(seed)
    n, d = num_nodes, channels
    out = (
        torch.randn(n, d, generator=g),
        random_edge_index(n, n, num_mesh_edges, g),
        torch.randn(num_mesh_edges, d, generator=g),
        random_edge_index(n, n, num_contact_edges, g),
        torch.randn(num_contact_edges, d, generator=g),
    )
    if mask_drop_prob is None:
        return out
    return (*out, torch.rand(num_contact_edges, generator=g) > mask_drop_prob)


def random_inter_level_inputs(
    num_src: int, num_dst: int, num_edges: int, channels: int, seed: int = 0
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Random arguments of :class:`~torch_ampn.nn.InterLevelConv`, drawn from one seeded generator.

    Args:
        num_src: Number of sending nodes ``N_src``.
        num_dst: Number of receiving nodes ``N_dst``.
        num_edges: Number of edges ``E`` (random pairs, may repeat).
        channels: Feature size ``d`` of nodes and edges.
        seed: Seed of the generator all tensors are drawn from, in the order returned.

    Returns:
        ``(x_src [N_src, d], x_dst [N_dst, d], edge_index [2, E], edge_attr [E, d])``; rows of
        ``edge_index`` are ``(source j, target i)``.
    """
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(num_src, channels, generator=g),
        torch.randn(num_dst, channels, generator=g),
        random_edge_index(num_src, num_dst, num_edges, g),
        torch.randn(num_edges, channels, generator=g),
    )


def layer_norm_mlp_reference(mlp: LayerNormMLP, z: Tensor) -> Tensor:
    """``mlp(z)`` written out for one vector in float64: LayerNorm -> Linear -> SiLU -> Linear.

    Args:
        mlp: The :class:`~torch_ampn.nn.LayerNormMLP` whose parameters are used (any dtype).
        z: One float64 input vector ``[F_in]``.

    Returns:
        The float64 output ``[F_out]``.
    """
    mu = z.mean()
    var = ((z - mu) ** 2).mean()  # biased, as LayerNorm's
    z = (z - mu) / torch.sqrt(var + mlp.norm.eps) * mlp.norm.weight.double() + mlp.norm.bias.double()
    h = mlp.lin1.weight.double() @ z + mlp.lin1.bias.double()  # [H]
    h = h / (1.0 + torch.exp(-h))  # SiLU
    return mlp.lin2.weight.double() @ h + mlp.lin2.bias.double()


def aggregate_reference(values: list[Tensor], aggr: str, channels: int) -> Tensor:
    """The ``"max"``, ``"sum"`` or ``"mean"`` of a node's incoming messages; zeros if it has none.

    Args:
        values: The messages, each ``[channels]`` float64 (may be empty).
        aggr: ``"max"``, ``"sum"`` or ``"mean"``.
        channels: Message size, for the zero vector of a node without messages.

    Returns:
        ``[channels]`` float64.
    """
    if not values:
        return torch.zeros(channels, dtype=torch.float64)
    stacked = torch.stack(values)  # [M, channels]
    return {"max": stacked.max(0).values, "sum": stacked.sum(0), "mean": stacked.mean(0)}[aggr]


def contact_edges_brute_force(pos: Tensor, component: Tensor, r: float, k: int) -> Tensor:
    """Reference contact edges by an all-pairs search (small graphs only, O(N^2)).

    For every target ``i`` and every component ``c != component[i]``: the ``k`` nearest nodes
    ``j`` of ``c`` with ``|pos_j - pos_i| <= r`` (ties by index). Rows ``(source j, target i)``,
    sorted by target (then component, then distance).
    """
    dist = torch.cdist(pos.double(), pos.double())  # [N, N]
    inf = torch.tensor(float("inf"), dtype=dist.dtype)
    src, dst = [], []
    for c in component.unique().tolist():
        allowed = (component == c).unsqueeze(0) & (component != c).unsqueeze(1) & (dist <= r)  # [N, N]
        d = torch.where(allowed, dist, inf)
        vals, order = torch.sort(d, dim=1, stable=True)  # nearest first, ties by index
        vals, order = vals[:, :k], order[:, :k]  # [N, k]
        valid = torch.isfinite(vals)
        target = torch.arange(pos.size(0)).unsqueeze(1).expand_as(order)
        src.append(order[valid])
        dst.append(target[valid])
    ei = torch.stack([torch.cat(src), torch.cat(dst)]) if src else torch.empty(2, 0, dtype=torch.long)
    perm = torch.argsort(ei[1], stable=True)  # by target, then as found
    return ei[:, perm]


def toy_hierarchy(
    nx: int = 6,
    ny: int = 5,
    num_components: int = 3,
    max_levels: int = 3,
    num_grippers: int = 2,
    contact_radius: float = 0.6,
    contact_k: int = 2,
    min_coarse_nodes: int = 2,
    seed: int = 0,
) -> HierarchicalData:
    """A small stacked-plate hierarchy with all fields of a forming step, for tests.

    ``num_components`` plates of ``nx x ny`` triangle cells, ``0.5`` apart; the last one is a
    punch (tool), the others plies. Fills ``l0``'s ``pos0``, ``pos`` (perturbed),
    ``prev_disp``, ``bc_disp`` (tool only), ``node_type``, ``component``, ``fiber`` (unit
    vectors on plies), graph-level ``gripper_pos`` / ``gripper_force`` ``[1, G, 3]``, and
    brute-force contact edges on every level from the root positions
    (:func:`contact_edges_brute_force`).
    """
    g = torch.Generator().manual_seed(seed)
    mesh = stacked_plates(nx, ny, num_components, size=(1.0, 1.0), gap=0.5)
    h = build_hierarchy(
        mesh.edge_index(), mesh.num_nodes, max_levels=max_levels, min_coarse_nodes=min_coarse_nodes
    )
    n = mesh.num_nodes
    node_type = mesh.node_type.clone()
    tool = mesh.component == num_components - 1
    node_type[tool] = int(NodeType.PUNCH)
    fine = h["l0"]
    fine.pos0 = mesh.pos
    fine.pos = mesh.pos + 0.05 * torch.randn(n, 3, generator=g)
    fine.prev_disp = 0.01 * torch.randn(n, 3, generator=g)
    fine.bc_disp = torch.where(tool[:, None], torch.tensor([0.0, 0.0, -0.02]), torch.zeros(3))
    angle = (mesh.component.float() * torch.pi / 4).unsqueeze(-1)
    fiber = torch.cat([angle.cos(), angle.sin(), torch.zeros_like(angle)], -1)
    fine.fiber = torch.where(tool[:, None], torch.zeros(3), fiber)
    fine.node_type = node_type
    fine.component = mesh.component
    h.gripper_pos = torch.rand(1, num_grippers, 3, generator=g)
    h.gripper_force = 100.0 * torch.rand(1, num_grippers, 3, generator=g)
    for k in range(h.num_levels):
        idx = h.fine_index(k)
        lk = level_name(k)
        h[lk, "contact", lk].edge_index = contact_edges_brute_force(
            fine.pos[idx], mesh.component[idx], contact_radius, contact_k
        )
    return h


def small_trajectory(steps: int = 4, seed: int = 0) -> Trajectory:
    """Two plies and a die with an arbitrary (random) motion; no simulator involved.

    Plies of ``3 x 2 x 2`` triangles (12 nodes each) at e3 = 0 and 0.5, a die of ``2 x 2`` quads
    (9 nodes) at e3 = -0.5 that stays put, the plies' nodes moving by a random walk with steps
    ``N(0, 0.1^2)`` per coordinate. One gripper between ply nodes 3 and 15, anchored at
    ``(10, 0, 0)`` with 42 N; fibres along e1; ``meta = {"seed": seed}``.

    Args:
        steps: Number of steps ``T`` after the initial state.
        seed: Seed of the motion.

    Returns:
        A :class:`~torch_ampn.data.Trajectory` with ``pos`` ``[T + 1, 33, 3]``.
    """
    g = torch.Generator().manual_seed(seed)
    parts = []
    for k in range(2):
        pos, cells = rectangle_mesh(3, 2, (3.0, 2.0), (0.0, 0.0, 0.5 * k))
        parts.append((pos, cells, NodeType.PLY))
    pos, cells = rectangle_mesh(2, 2, (3.0, 2.0), (0.0, 0.0, -0.5), cell_type="quad")
    parts.append((pos, cells, NodeType.DIE))
    pos0, all_cells, comp, types, offset = [], [], [], [], 0
    for c, (p, f, t) in enumerate(parts):
        pos0.append(p)
        all_cells.append(f + offset)
        comp.append(torch.full((p.size(0),), c))
        types.append(torch.full((p.size(0),), int(t)))
        offset += p.size(0)
    pos0 = torch.cat(pos0)  # [N, 3]
    n = pos0.size(0)
    motion = torch.cumsum(0.1 * torch.randn(steps, n, 3, generator=g), 0)  # [T, N, 3]
    node_type = torch.cat(types)
    motion[:, node_type == NodeType.DIE] = 0.0
    fiber = torch.zeros(n, 3)
    fiber[node_type == NodeType.PLY, 0] = 1.0
    return Trajectory(
        pos=torch.cat([pos0[None], pos0[None] + motion]),
        time=torch.linspace(0, 1, steps + 1),
        cells=all_cells,
        component=torch.cat(comp),
        node_type=node_type,
        fiber=fiber,
        names=["ply0", "ply1", "die"],
        gripper_nodes=torch.tensor([[3, 15]]),
        gripper_anchor=torch.tensor([[10.0, 0.0, 0.0]]),
        gripper_force=torch.tensor([42.0]),
        meta=dict(seed=seed),
    )
