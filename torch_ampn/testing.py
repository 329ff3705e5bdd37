"""Small helpers shared by the tests, in the spirit of ``torch_geometric.testing``.

Devices, brute-force reference graphs and a toy hierarchy with every feature a model needs.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torch_ampn.data import HierarchicalData, NodeType, build_hierarchy, level_name, stacked_plates

#: Devices to parametrise tests over: the CPU and, if present, CUDA.
DEVICES: list[str] = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


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
