"""Penalty contact with friction: plies against the analytic tools, and ply on ply."""

from __future__ import annotations

import torch
from torch import Tensor


def smooth_friction(
    f_normal: Tensor, v_rel: Tensor, normal: Tensor, mu: float, max_coeff: Tensor, v_eps: float = 0.1
) -> Tensor:
    """Regularised Coulomb friction opposing the tangential relative velocity.

    The force is ``-c v_t`` with ``c = mu |f_n| / sqrt(|v_t|^2 + v_eps^2)`` (Coulomb for
    sliding, viscous near sticking), and ``c`` is capped at ``max_coeff`` (``m / dt``) so
    that friction can stop a node within one explicit step but never reverse it.

    Args:
        f_normal: Normal force magnitude ``[M]`` (N).
        v_rel: Relative velocity of the node w.r.t. the surface ``[M, 3]`` (mm/s).
        normal: Unit surface normals ``[M, 3]``.
        mu: Friction coefficient.
        max_coeff: Cap of the viscous coefficient ``[M, 1]`` (N s/mm).
        v_eps: Velocity (mm/s) below which friction is viscous rather than Coulomb.

    Returns:
        Friction forces on the node ``[M, 3]``.
    """
    v_t = v_rel - (v_rel * normal).sum(1, keepdim=True) * normal
    speed = torch.sqrt((v_t * v_t).sum(1, keepdim=True) + v_eps * v_eps)
    coeff = torch.minimum(mu * f_normal[:, None] / speed, max_coeff)
    return -coeff * v_t


def height_field_contact(
    x: Tensor,
    surface_z: Tensor,
    surface_grad: Tensor,
    side: float,
    offset: Tensor,
    stiffness: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Penalty force keeping nodes on one side of a height field ``z = s(x, y)``.

    Args:
        x: Node positions ``[N, 3]``.
        surface_z: ``s`` at the nodes' ``(x, y)``, ``[N]``.
        surface_grad: ``grad s`` there, ``[N, 2]``.
        side: ``+1``: nodes must stay above ``s + offset`` (die); ``-1``: below ``s - offset`` (punch).
        offset: Per-node distance to keep from the surface ``[N]`` (half the stack below/above).
        stiffness: Penalty stiffness (N/mm).

    Returns:
        ``(force [N, 3], normal force magnitude [N], unit normal [N, 3])``; the normal points
        from the tool into the laminate.
    """
    normal = torch.cat([-side * surface_grad, torch.full_like(surface_z[:, None], side)], 1)
    inv_len = torch.rsqrt(1.0 + (surface_grad * surface_grad).sum(1))
    normal = normal * inv_len[:, None]
    # vertical penetration, converted to the distance along the normal
    pen = (side * (surface_z + side * offset - x[:, 2])).clamp_min(0.0) * inv_len
    f_n = stiffness * pen
    return f_n[:, None] * normal, f_n, normal


def vertex_normals(x: Tensor, triangles: Tensor) -> Tensor:
    """Area-weighted unit vertex normals ``[N, 3]`` of a triangle mesh (counter-clockwise cells)."""
    x0, x1, x2 = (x[triangles[:, i]] for i in range(3))
    fn = torch.linalg.cross(x1 - x0, x2 - x0)  # twice the area times the unit normal
    out = torch.zeros_like(x)
    for i in range(3):
        out.index_add_(0, triangles[:, i], fn)
    return out / out.norm(dim=1, keepdim=True).clamp_min(1e-12)


def nearest_nodes(query: Tensor, target: Tensor, chunk: int = 4096) -> Tensor:
    """Index into ``target`` ``[M, 3]`` of the nearest point to each ``query`` ``[Q, 3]``."""
    out = []
    for start in range(0, query.size(0), chunk):
        out.append(torch.cdist(query[start : start + chunk], target).argmin(1))
    return torch.cat(out)


def ply_on_ply_normal(
    x: Tensor, upper: Tensor, lower: Tensor, normals: Tensor, thickness: float, stiffness: float
) -> tuple[Tensor, Tensor]:
    """Normal force magnitude ``[M]`` (N) and unit normal ``[M, 3]`` of every ply-on-ply pair.

    Each ``upper[m]`` node must stay ``thickness`` above the tangent plane of its partner
    ``lower[m]`` (a nearby node of the ply below, with unit normal ``normals[lower[m]]``).
    Penetrations deeper than twice the thickness are ignored (wrong partner). The penalty
    energy of a pair is ``f_n^2 / (2 stiffness)``.
    """
    n = normals[lower]  # [M, 3]
    gap = ((x[upper] - x[lower]) * n).sum(1) - thickness
    # A node more than one thickness "through" its partner's plane has a wrong partner (a
    # fold, or a partner on the other side of a wrinkle): no force rather than a huge one.
    pen = (-gap).clamp_min(0.0)
    return stiffness * torch.where(pen < 2.0 * thickness, pen, torch.zeros_like(pen)), n


def ply_on_ply_contact(
    x: Tensor,
    v: Tensor,
    upper: Tensor,
    lower: Tensor,
    normals: Tensor,
    thickness: float,
    stiffness: float,
    mu: float,
    max_coeff: Tensor,
    damping: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Node-to-surface penalty contact with friction between pairs of stacked plies.

    The normal force is :func:`ply_on_ply_normal`'s; ``max_coeff`` ``[M, 1]`` caps the
    friction coefficient (see :func:`smooth_friction`); ``damping`` ``[M, 1]`` (N s/mm), if
    given, resists the normal relative velocity of the pairs in contact (contact damping).

    Returns:
        Normal, friction and damping forces ``[N, 3]`` each (equal and opposite on the two nodes
        of a pair).
    """
    f_n, n = ply_on_ply_normal(x, upper, lower, normals, thickness, stiffness)
    v_rel = v[upper] - v[lower]
    parts = [f_n[:, None] * n, smooth_friction(f_n, v_rel, n, mu, max_coeff)]
    if damping is not None:
        parts.append(contact_damping(f_n, v_rel, n, damping))
    out = [torch.zeros_like(x).index_add_(0, upper, f).index_add_(0, lower, -f) for f in parts]
    return out[0], out[1], out[2] if damping is not None else torch.zeros_like(x)


def contact_damping(f_normal: Tensor, v_rel: Tensor, normal: Tensor, coeff: Tensor) -> Tensor:
    """Viscous contact damping ``-c (v_rel . n) n`` where the contact is closed (``f_normal > 0``).

    As explicit codes damp penalty contact (a fraction of the critical damping of the penalty
    spring on the node's mass), so that nodes do not chatter against a surface.

    Args:
        f_normal: Normal force magnitude ``[M]``; zero where the contact is open.
        v_rel: Relative velocity ``[M, 3]``.
        normal: Unit normals ``[M, 3]``.
        coeff: Damping coefficients ``[M, 1]`` (N s/mm).
    """
    closed = (f_normal > 0).to(v_rel.dtype)[:, None]
    return -(closed * coeff) * (v_rel * normal).sum(1, keepdim=True) * normal
