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
    parts = _pair_forces(f_n, n, v[upper] - v[lower], mu, max_coeff, damping)
    out = [torch.zeros_like(x).index_add_(0, upper, f).index_add_(0, lower, -f) for f in parts]
    return out[0], out[1], out[2] if damping is not None else torch.zeros_like(x)


def _pair_forces(
    f_n: Tensor, n: Tensor, v_rel: Tensor, mu: float, max_coeff: Tensor, damping: Tensor | None
) -> list[Tensor]:
    """A pair's normal, friction and (with ``damping``) damping force on the upper node, ``[M, 3]`` each."""
    parts = [f_n[:, None] * n, smooth_friction(f_n, v_rel, n, mu, max_coeff)]
    if damping is not None:
        parts.append(contact_damping(f_n, v_rel, n, damping))
    return parts


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


def incident_faces(triangles: Tensor, num_nodes: int) -> Tensor:
    """The triangles around every node, ``[N, D]`` (``D`` the largest count; short rows repeat their first).

    Nodes without a triangle get triangle 0 (they are never contact partners).
    """
    node = triangles.reshape(-1)  # [3F]
    face = torch.arange(triangles.size(0)).repeat_interleave(3)
    order = torch.argsort(node, stable=True)
    node, face = node[order], face[order]
    count = torch.bincount(node, minlength=num_nodes)
    width = int(count.max()) if count.numel() else 1
    start = torch.cumsum(count, 0) - count
    rank = torch.arange(node.numel()) - start[node]
    out = torch.zeros(num_nodes, width, dtype=torch.long)
    out[node, rank] = face
    first = out[:, :1].expand(-1, width)
    pad = torch.arange(width)[None] >= count[:, None]
    return torch.where(pad, first, out)


def _barycentric(ab: Tensor, ac: Tensor, ap: Tensor) -> Tensor:
    """Barycentric weights ``[..., 3]`` of the in-plane part of ``ap`` in the triangle ``(ab, ac)``."""
    d00, d01, d11 = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d20, d21 = (ap * ab).sum(-1), (ap * ac).sum(-1)
    denom = (d00 * d11 - d01 * d01).clamp_min(1e-24)
    w1, w2 = (d11 * d20 - d01 * d21) / denom, (d00 * d21 - d01 * d20) / denom
    return torch.stack([1.0 - w1 - w2, w1, w2], -1)


def closest_points_on_triangles(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """Closest point to ``p`` on each triangle ``(a, b, c)`` and its barycentric weights.

    Args:
        p: Points ``[..., 3]``.
        a: First corners, broadcastable to ``p``.
        b: Second corners.
        c: Third corners.

    Returns:
        ``(point [..., 3], weights [..., 3])`` with ``point = w0 a + w1 b + w2 c``.
    """
    ab, ac = b - a, c - a
    n = torch.linalg.cross(ab, ac)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q = p - ((p - a) * n).sum(-1, keepdim=True) * n  # projection onto the plane
    inside = _barycentric(ab, ac, q - a)
    candidates, weights = [q], [inside]
    for i, (s, e) in enumerate(((a, b), (b, c), (c, a))):  # the three edges
        se = e - s
        t = (((p - s) * se).sum(-1) / (se * se).sum(-1).clamp_min(1e-24)).clamp(0.0, 1.0)
        candidates.append(s + t[..., None] * se)
        w = torch.zeros_like(inside)
        w[..., i] = 1.0 - t
        w[..., (i + 1) % 3] = t
        weights.append(w)
    is_inside = (inside >= 0).all(-1)
    dist = torch.stack([((p - cand) ** 2).sum(-1) for cand in candidates], -1)  # [..., 4]
    dist[..., 0] = torch.where(is_inside, dist[..., 0], torch.full_like(dist[..., 0], float("inf")))
    best = dist.argmin(-1)
    point = torch.gather(torch.stack(candidates, -2), -2, best[..., None, None].expand(*best.shape, 1, 3))
    weight = torch.gather(torch.stack(weights, -2), -2, best[..., None, None].expand(*best.shape, 1, 3))
    return point.squeeze(-2), weight.squeeze(-2)


def faded_penalty(pen: Tensor, thickness: float, stiffness: float) -> tuple[Tensor, Tensor]:
    """Normal force ``[M]`` and energy ``[M]`` of a penalty that fades out past one thickness.

    ``k pen`` up to ``pen = thickness``, then falling linearly to zero at twice the thickness
    (a partner that deep is a wrong one: a fold, or the other side of a wrinkle), and zero
    beyond: a continuous force, so the potential is conservative in the gap.
    """
    h = thickness
    pen = pen.clamp_min(0.0)
    force = stiffness * torch.where(pen <= h, pen, (2.0 * h - pen).clamp_min(0.0))
    near = 0.5 * stiffness * pen * pen
    far = stiffness * h * h - 0.5 * stiffness * (2.0 * h - pen.clamp_max(2.0 * h)) ** 2
    return force, torch.where(pen <= h, near, far)


def ply_on_face_gap(
    x: Tensor, upper: Tensor, faces: Tensor, triangles: Tensor, thickness: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Penetration of every upper node into the ply below, against its closest candidate face.

    Args:
        x: Node positions ``[N, 3]``.
        upper: Upper nodes ``[M]``.
        faces: Candidate triangles of the ply below per upper node ``[M, K]`` (e.g. those
            around its nearest node there).
        triangles: All triangles ``[F, 3]`` (counter-clockwise: normals towards the ply above).
        thickness: Distance to keep from the face's plane.

    Returns:
        ``(pen [M], normal [M, 3], corners [M, 3], weights [M, 3], best [M])``: penetration
        (positive when closer than ``thickness``), the face's unit normal, the face's nodes,
        the closest point's barycentric weights on them, and which candidate it is.
    """
    corners = triangles[faces]  # [M, K, 3]
    a, b, c = (x[corners[..., i]] for i in range(3))  # [M, K, 3] each
    p = x[upper][:, None]  # [M, 1, 3]
    point, weight = closest_points_on_triangles(p, a, b, c)
    best = ((p - point) ** 2).sum(-1).argmin(1)  # [M]
    pick = torch.arange(upper.numel(), device=x.device)
    a, b, c, point, weight = (
        a[pick, best],
        b[pick, best],
        c[pick, best],
        point[pick, best],
        weight[pick, best],
    )
    n = torch.linalg.cross(b - a, c - a)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    pen = thickness - ((x[upper] - point) * n).sum(-1)
    return pen, n, corners[pick, best], weight, best


def face_plane(
    x: Tensor, upper: Tensor, faces: Tensor, triangles: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each upper node's height above its partner face's plane, and where it projects onto the face.

    Args:
        x: Node positions ``[N, 3]``.
        upper: Upper nodes ``[M]``.
        faces: Each upper node's partner triangle ``[M]`` (e.g. from :func:`ply_on_face_gap`).
        triangles: All triangles ``[F, 3]`` (counter-clockwise: normals towards the ply above).

    Returns:
        ``(height [M], normal [M, 3], corners [M, 3], weights [M, 3])``: the signed distance
        from the face's plane (the same as from the face's closest point, which lies in it),
        the unit normal, the face's nodes, and the barycentric weights of the node's projection
        clamped into the face (where the reaction goes and whose velocity friction sees).
    """
    corners = triangles[faces]  # [M, 3]
    a, b, c = x[corners[:, 0]], x[corners[:, 1]], x[corners[:, 2]]
    ab, ac, ap = b - a, c - a, x[upper] - a
    n = torch.linalg.cross(ab, ac)
    n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)
    weights = _barycentric(ab, ac, ap).clamp_min(0.0)
    weights = weights / weights.sum(1, keepdim=True)
    return (ap * n).sum(1), n, corners, weights


def ply_on_face_contact(
    x: Tensor,
    v: Tensor,
    upper: Tensor,
    faces: Tensor,
    triangles: Tensor,
    thickness: float,
    stiffness: float,
    mu: float,
    max_coeff: Tensor,
    damping: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Node-to-face penalty contact with friction between stacked plies.

    Each upper node keeps ``thickness`` from the plane of its partner face ``faces`` ``[M]``
    (:func:`face_plane`); the penalty fades out past one thickness (:func:`faded_penalty`);
    the force on the node is balanced on the face's three nodes by the projection's
    barycentric weights; friction and ``damping`` act on the velocity relative to that point.

    Returns:
        Normal, friction and damping forces ``[N, 3]`` each.
    """
    height, n, corners, weight = face_plane(x, upper, faces, triangles)
    f_n, _ = faded_penalty(thickness - height, thickness, stiffness)
    v_point = (weight[..., None] * v[corners]).sum(1)  # [M, 3]
    parts = _pair_forces(f_n, n, v[upper] - v_point, mu, max_coeff, damping)
    out = []
    for f in parts:
        total = torch.zeros_like(x).index_add_(0, upper, f)
        out.append(total.index_add_(0, corners.reshape(-1), -(weight[..., None] * f[:, None]).reshape(-1, 3)))
    return out[0], out[1], out[2] if damping is not None else torch.zeros_like(x)
