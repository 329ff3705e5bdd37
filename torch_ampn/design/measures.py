"""Part-quality measures of a formed laminate, for simulated and predicted positions alike.

Every measure takes the trajectory that defines the part (its meshes, components, node types,
fibre directions and its first saved state as the reference, flat or not) and the positions
to judge, ``pos`` ``[N, 3]`` (usually the last state of a simulated or predicted rollout).
Lengths are in mm, angles in degrees.

* :func:`wrinkle_field`: out-of-plane waviness of each ply: the distance of each ply node from
  a quadratic surface fitted (least squares) to the ply around it, within ``radius`` in the
  reference state, along that surface's normal. A smooth formed shape (a dome of curvature
  radius well above ``radius``) gives about 0; a wave of wavelength up to about ``radius`` gives
  its amplitude back.
* :func:`draw_in_field`: in-plane displacement of each ply's free edge towards the inside of the
  blank, measured in the reference plane of the edge (plan view), per boundary node.
* :func:`shear_field`: in-plane shear angle of every ply cell, the change of the angle between
  the fibre and the transverse direction (0 for any rigid motion).
* :func:`penetration_field`: depth of each ply node behind the nearest tool node's tangent plane.
* :func:`part_quality`: the scalar summaries of all four, by name (:data:`MEASURES`).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory

#: The scalar measures of :func:`part_quality`: name -> (unit, description).
MEASURES: dict[str, tuple[str, str]] = {
    "wrinkle_amplitude": ("mm", "largest |out-of-plane waviness| over the ply nodes"),
    "wrinkle_rms": ("mm", "RMS out-of-plane waviness over the ply nodes"),
    "draw_in_mean": ("mm", "mean draw-in of the plies' free edges"),
    "draw_in_max": ("mm", "largest draw-in of any free-edge node"),
    "shear_max": ("deg", "largest |in-plane shear angle| of any ply cell"),
    "shear_rms": ("deg", "RMS in-plane shear angle over the ply cells"),
    "penetration_max": ("mm", "deepest ply node behind a tool surface"),
}


def ply_components(traj: Trajectory) -> list[int]:
    """The components whose nodes are all ``PLY`` nodes, in order."""
    out = []
    for c in range(len(traj.cells)):
        types = traj.node_type[traj.component == c]
        if types.numel() and bool((types == NodeType.PLY).all()):
            out.append(c)
    return out


def _check_pos(traj: Trajectory, pos: Tensor) -> Tensor:
    if pos.dim() != 2 or pos.shape != (traj.num_nodes, 3):
        raise ValueError(f"pos must be [N, 3] = [{traj.num_nodes}, 3] for this part, got {list(pos.shape)}")
    return pos.double()


def median_edge_length(traj: Trajectory) -> float:
    """The median length of the plies' mesh edges in the reference state (mm)."""
    from torch_ampn.data.mesh import cells_to_edge_index

    ref = traj.pos[0].double()
    lengths = []
    for c in ply_components(traj):
        edges = cells_to_edge_index(traj.cells[c])
        lengths.append((ref[edges[0]] - ref[edges[1]]).norm(dim=1))
    if not lengths:
        raise ValueError("the part has no ply component (no component of PLY nodes only)")
    return float(torch.cat(lengths).median())


def _local_frames(ref: Tensor, weights: Tensor, up: Tensor) -> Tensor:
    """Right-handed orthonormal frames ``[n, 3, 3]`` (tangent 1, tangent 2, normal) of neighbourhoods.

    ``ref`` ``[m, 3]`` reference positions, ``weights`` ``[n, m]`` (0/1 neighbourhood of each
    node), ``up`` ``[3]``: the side the normals point to (the ply's mean cell normal), so that
    the waviness has one sign convention over the ply.
    """
    count = weights.sum(1, keepdim=True)  # [n, 1]
    centre = weights @ ref / count  # [n, 3]
    d = ref.unsqueeze(0) - centre.unsqueeze(1)  # [n, m, 3]
    cov = torch.einsum("nm,nmi,nmj->nij", weights, d, d)  # [n, 3, 3]
    _, vectors = torch.linalg.eigh(cov)  # ascending: the normal is the smallest
    normal = vectors[..., 0] * torch.where((vectors[..., 0] @ up) < 0, -1.0, 1.0).unsqueeze(1).to(ref.dtype)
    t1 = vectors[..., 2]
    return torch.stack([t1, torch.linalg.cross(normal, t1), normal], 1)


def _mean_cell_normal(ref: Tensor, cells: Tensor) -> Tensor:
    """The sum of a mesh's cell normals ``[3]`` (from the corner winding), normalised."""
    q = ref[cells]
    n = torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]).sum(0)
    return n / n.norm().clamp_min(1e-12)


class WrinkleOperator:
    """The linear fits of :func:`wrinkle_field` for one part, built once from its reference state.

    Around each ply node ``i``, the ply's nodes within ``radius`` of it in the reference state
    (``traj.pos[0]``) are mapped to the node's reference tangent plane ``(u, v)``; the least-
    squares quadratic ``x(u, v)`` through positions ``Y`` of those nodes has coefficients
    ``P_i Y`` with ``P_i = (Phi^T Phi)^+ Phi^T`` ``[6, K]``, which depends on the reference only.
    Judging many settings of one part (a design study) then costs one product per call.

    Args:
        traj: The part (meshes, components, node types, reference state).
        radius: Neighbourhood radius in mm (default: 3 median ply edge lengths): waves up to
            about this wavelength count as wrinkles, longer ones as the part's shape.
        chunk: Nodes set up at a time (memory ``chunk x ply nodes``).
    """

    def __init__(self, traj: Trajectory, radius: float | None = None, chunk: int = 256) -> None:
        self.radius = 3.0 * median_edge_length(traj) if radius is None else float(radius)
        if self.radius <= 0:
            raise ValueError(f"radius must be > 0 mm, got {self.radius}")
        self.num_nodes = traj.num_nodes
        self.reference = traj.pos[0].double().clone()
        nodes, neighbours, operators = [], [], []
        for c in ply_components(traj):
            idx = (traj.component == c).nonzero().squeeze(1)
            ref = self.reference[idx]  # [m, 3]
            up = _mean_cell_normal(self.reference, traj.cells[c])
            for start in range(0, idx.numel(), chunk):
                rows = torch.arange(start, min(start + chunk, idx.numel()))
                w = torch.cdist(ref[rows], ref) <= self.radius  # [n, m]
                count = w.sum(1)
                if bool((count < 6).any()):
                    raise ValueError(
                        f"wrinkle radius {self.radius:g} mm holds fewer than 6 nodes of ply "
                        f"{traj.names[c]!r} around some node: choose a larger radius"
                    )
                frames = _local_frames(ref, w.double(), up)  # [n, 3, 3]
                k = int(count.max())
                # Padded neighbour lists [n, K] (padding: the node itself, with weight 0).
                order = torch.sort(w.to(torch.int8), dim=1, descending=True, stable=True).indices[:, :k]
                valid = torch.gather(w, 1, order)  # [n, K]
                nbr = torch.where(valid, order, rows[:, None])
                d = (ref[nbr] - ref[rows].unsqueeze(1)) / self.radius  # [n, K, 3]
                u = torch.einsum("nki,ni->nk", d, frames[:, 0])
                v = torch.einsum("nki,ni->nk", d, frames[:, 1])
                basis = torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v], -1)
                basis = basis * valid.unsqueeze(-1)  # [n, K, 6]
                gram = basis.transpose(1, 2) @ basis  # [n, 6, 6]
                operators.append(torch.linalg.pinv(gram, hermitian=True) @ basis.transpose(1, 2))  # [n, 6, K]
                nodes.append(idx[rows])
                neighbours.append(idx[nbr])
        if not nodes:
            raise ValueError("the part has no ply component (no component of PLY nodes only)")
        self.nodes = torch.cat(nodes)  # [M]
        width = max(n.size(1) for n in neighbours)
        self.neighbours = torch.cat(
            [torch.nn.functional.pad(n, (0, width - n.size(1)), value=0) for n in neighbours]
        )
        self.operators = torch.cat([torch.nn.functional.pad(o, (0, width - o.size(2))) for o in operators])

    def applies_to(self, traj: Trajectory) -> bool:
        """Whether ``traj`` is the same part (same node count and reference state)."""
        return traj.num_nodes == self.num_nodes and torch.equal(traj.pos[0].double(), self.reference)

    def __call__(self, pos: Tensor) -> Tensor:
        """Waviness ``[N]`` (float64; 0 at the tools' nodes) of positions ``pos`` ``[N, 3]``."""
        if pos.shape != (self.num_nodes, 3):
            raise ValueError(
                f"pos must be [N, 3] = [{self.num_nodes}, 3] for this part, got {list(pos.shape)}"
            )
        x = pos.double()
        coef = self.operators @ x[self.neighbours]  # [M, 6, 3]
        normal = torch.linalg.cross(coef[:, 1], coef[:, 2])
        normal = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-12)
        out = torch.zeros(self.num_nodes, dtype=torch.float64)
        out[self.nodes] = ((x[self.nodes] - coef[:, 0]) * normal).sum(1)
        return out


def wrinkle_field(traj: Trajectory, pos: Tensor, radius: float | None = None) -> Tensor:
    """Signed out-of-plane waviness of every ply node (mm; 0 at the tools' nodes), ``[N]`` float64.

    The distance of each ply node at ``pos`` ``[N, 3]`` from the quadratic surface fitted to its
    ply's nodes within ``radius`` of it (in the reference state), along that surface's normal;
    see :class:`WrinkleOperator` (build one to judge many positions of one part).
    """
    _check_pos(traj, pos)
    return WrinkleOperator(traj, radius)(pos)


def _boundary_normals(ref: Tensor, cells: Tensor) -> tuple[Tensor, Tensor]:
    """Boundary nodes of one ply mesh and their outward unit normals in the reference surface.

    ``ref`` ``[N, 3]`` all nodes' reference positions, ``cells`` ``[F, k]`` (global indices).
    Returns ``(nodes [B], normals [B, 3])``, global node indices.
    """
    k = cells.size(1)
    edges = torch.stack([cells, cells.roll(-1, 1)], -1).reshape(-1, 2)  # [F*k, 2] (a, b) per cell side
    owner = torch.arange(cells.size(0)).repeat_interleave(k)
    key = torch.sort(edges, 1).values
    _, inverse, counts = torch.unique(key, dim=0, return_inverse=True, return_counts=True)
    boundary = counts[inverse] == 1  # [F*k]
    a, b = edges[boundary, 0], edges[boundary, 1]
    centroid = ref[cells[owner[boundary]]].mean(1)  # [E_b, 3]
    tangent = ref[b] - ref[a]
    mid = 0.5 * (ref[a] + ref[b])
    outward = mid - centroid
    # The part of (mid - centroid) normal to the edge, in the cell's plane: the edge's outward normal.
    tangent_hat = tangent / tangent.norm(dim=1, keepdim=True)
    normal = outward - (outward * tangent_hat).sum(1, keepdim=True) * tangent_hat
    normal = normal / normal.norm(dim=1, keepdim=True) * tangent.norm(dim=1, keepdim=True)  # length-weighted
    nodes = torch.unique(torch.cat([a, b]))
    acc = torch.zeros(ref.size(0), 3, dtype=ref.dtype)
    acc.index_add_(0, a, normal)
    acc.index_add_(0, b, normal)
    acc = acc[nodes]
    return nodes, acc / acc.norm(dim=1, keepdim=True).clamp_min(1e-12)


_BOUNDARY_CACHE: dict[tuple[bytes, bytes], tuple[Tensor, Tensor]] = {}


def _cached_boundary_normals(ref: Tensor, cells: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_boundary_normals` of a ply, remembered by content (a study judges one part many times)."""
    key = (ref.numpy().tobytes(), cells.numpy().tobytes())
    if key not in _BOUNDARY_CACHE:
        if len(_BOUNDARY_CACHE) >= 64:
            _BOUNDARY_CACHE.pop(next(iter(_BOUNDARY_CACHE)))
        _BOUNDARY_CACHE[key] = _boundary_normals(ref, cells)
    return _BOUNDARY_CACHE[key]


def draw_in_field(traj: Trajectory, pos: Tensor) -> tuple[Tensor, Tensor]:
    """Draw-in of every ply's free edge (mm): the boundary nodes and their inward in-plane displacement.

    For each boundary node of a ply mesh, ``-(pos - ref) . m`` with ``m`` the edge's outward unit
    normal in the reference surface: positive where the edge moved towards the inside of the
    blank (plan view, as draw-in is measured on a formed part), negative where it moved out.

    Returns:
        ``(nodes [B], draw_in [B])``: global node indices and their draw-in (float64).
    """
    x = _check_pos(traj, pos)
    ref_all = traj.pos[0].double()
    nodes, values = [], []
    for c in ply_components(traj):
        g, normal = _cached_boundary_normals(ref_all, traj.cells[c])
        nodes.append(g)
        values.append(-((x[g] - ref_all[g]) * normal).sum(1))
    if not nodes:
        raise ValueError("the part has no ply component (no component of PLY nodes only)")
    return torch.cat(nodes), torch.cat(values)


def _cell_vectors(p: Tensor, cells: Tensor) -> tuple[Tensor, Tensor]:
    """Two in-plane vectors ``[F, 3]`` of every triangle (sides) or quad (mid-side to mid-side)."""
    q = p[cells]  # [F, k, 3]
    if cells.size(1) == 3:
        return q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    return 0.5 * (q[:, 1] + q[:, 2] - q[:, 0] - q[:, 3]), 0.5 * (q[:, 2] + q[:, 3] - q[:, 0] - q[:, 1])


def shear_field(traj: Trajectory, pos: Tensor) -> tuple[Tensor, Tensor]:
    """In-plane shear angle of every ply cell (degrees), from its fibre and transverse directions.

    In each cell the reference fibre direction ``a`` (the mean of its nodes' ``traj.fiber``,
    projected on the cell's reference plane) and the transverse direction ``b = n x a`` are
    mapped by the cell's deformation gradient ``F`` to ``f = F a`` and ``t = F b``; the shear
    angle is ``asin(f . t / (|f| |t|))``: 0 for a rigid motion, ``g`` for a simple shear of
    ``tan g`` along the fibres.

    Returns:
        ``(components [F_total], shear [F_total])``: the ply component of each cell and its angle.
    """
    x = _check_pos(traj, pos)
    ref = traj.pos[0].double()
    comps, values = [], []
    for c in ply_components(traj):
        g = traj.cells[c]  # [F, k] global indices
        r1, r2 = _cell_vectors(ref, g)  # [F, 3] each
        c1, c2 = _cell_vectors(x, g)
        n = torch.linalg.cross(r1, r2)
        n = n / n.norm(dim=1, keepdim=True)
        fib = traj.fiber.double()[g].mean(1)
        a = fib - (fib * n).sum(1, keepdim=True) * n
        a = a / a.norm(dim=1, keepdim=True)
        b = torch.linalg.cross(n, a)
        # F [r1 r2] = [c1 c2], r in (a, b) coordinates: F = [c1 c2] R^-1, R = [[a.r1, a.r2], [b.r1, b.r2]]
        r = torch.stack([torch.stack([(r1 * e).sum(1), (r2 * e).sum(1)], -1) for e in (a, b)], 1)  # [F, 2, 2]
        grad = torch.stack([c1, c2], -1) @ torch.linalg.inv(r)  # [F, 3, 2]
        f, t = grad[..., 0], grad[..., 1]  # images of a and b
        cos = (f * t).sum(1) / (f.norm(dim=1) * t.norm(dim=1))
        comps.append(torch.full((g.size(0),), c))
        values.append(torch.rad2deg(torch.asin(cos.clamp(-1.0, 1.0))))
    if not comps:
        raise ValueError("the part has no ply component (no component of PLY nodes only)")
    return torch.cat(comps), torch.cat(values)


def penetration_field(traj: Trajectory, pos: Tensor, tool_pos: Tensor | None = None) -> Tensor:
    """Depth of every ply node behind the nearest tool node's tangent plane (mm, >= 0; 0 at tools).

    Each tool (a component of non-``PLY`` nodes) gets vertex normals from its cells, oriented
    towards the plies of the reference state (by majority over its vertices). A ply node
    behind the tangent plane of its nearest tool vertex (of any tool) by ``d`` gets ``d``.

    Args:
        traj: The part.
        pos: Positions ``[N, 3]``; the tools' positions are taken from it unless ``tool_pos``.
        tool_pos: Positions ``[N, 3]`` to take the tools' nodes from (e.g. the simulated state).
    """
    x = _check_pos(traj, pos)
    tools_x = x if tool_pos is None else _check_pos(traj, tool_pos)
    ref = traj.pos[0].double()
    ply = traj.node_type == NodeType.PLY
    plies = set(ply_components(traj))
    vertices, normals = [], []
    for c in range(len(traj.cells)):
        if c in plies:
            continue
        idx = (traj.component == c).nonzero().squeeze(1)
        normals.append(_vertex_normals(tools_x, ref, traj.cells[c], ref[ply])[idx])
        vertices.append(idx)
    out = torch.zeros(traj.num_nodes, dtype=torch.float64)
    if not vertices:
        return out
    v, n = torch.cat(vertices), torch.cat(normals)
    p = ply.nonzero().squeeze(1)
    nearest = torch.cdist(x[p], tools_x[v]).argmin(1)
    depth = -((x[p] - tools_x[v[nearest]]) * n[nearest]).sum(1)
    out[p] = depth.clamp_min(0.0)
    return out


def _vertex_normals(x: Tensor, ref: Tensor, cells: Tensor, ply_ref: Tensor) -> Tensor:
    """Unit vertex normals ``[N, 3]`` of one tool's ``cells`` at ``x`` (0 off the tool).

    Oriented towards the reference plies ``ply_ref`` (by majority over the tool's vertices).
    """
    normal = torch.zeros_like(x)
    k = cells.size(1)
    for j in range(k):  # corner normals, area-weighted by the cross product's length
        a, b, c = x[cells[:, j]], x[cells[:, (j + 1) % k]], x[cells[:, (j - 1) % k]]
        normal.index_add_(0, cells[:, j], torch.linalg.cross(b - a, c - a))
    normal = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-12)
    nodes = torch.unique(cells)
    nearest = torch.cdist(ref[nodes], ply_ref).argmin(1)
    towards = ((ply_ref[nearest] - ref[nodes]) * normal[nodes]).sum(1)
    return normal if float(torch.sign(towards).sum()) >= 0 else -normal


def part_quality(
    traj: Trajectory,
    pos: Tensor,
    wrinkle_radius: float | None = None,
    wrinkle: WrinkleOperator | None = None,
    names: Iterable[str] | None = None,
) -> dict[str, float]:
    """The scalar measures of :data:`MEASURES` for positions ``pos`` ``[N, 3]`` of the part ``traj``.

    ``wrinkle``: a :class:`WrinkleOperator` of this part built before (else one is built with
    ``wrinkle_radius``). ``names``: only these measures (and only their fields are computed);
    default all.
    """
    _check_pos(traj, pos)
    wanted = list(MEASURES) if names is None else list(names)
    unknown = sorted(set(wanted) - set(MEASURES))
    if unknown:
        raise ValueError(f"unknown measures {unknown}; choose from {sorted(MEASURES)}")
    fields = {name.split("_")[0] for name in wanted}  # wrinkle, draw, shear, penetration
    out: dict[str, float] = {}
    if "wrinkle" in fields:
        if wrinkle is None or not wrinkle.applies_to(traj):
            wrinkle = WrinkleOperator(traj, wrinkle_radius)
        w = wrinkle(pos)[traj.node_type == NodeType.PLY]
        out |= {"wrinkle_amplitude": float(w.abs().max()), "wrinkle_rms": float(w.square().mean().sqrt())}
    if "draw" in fields:
        _, draw_in = draw_in_field(traj, pos)
        out |= {"draw_in_mean": float(draw_in.mean()), "draw_in_max": float(draw_in.max())}
    if "shear" in fields:
        _, shear = shear_field(traj, pos)
        out |= {"shear_max": float(shear.abs().max()), "shear_rms": float(shear.square().mean().sqrt())}
    if "penetration" in fields:
        out["penetration_max"] = float(penetration_field(traj, pos).max())
    return {name: out[name] for name in wanted}


__all__ = [
    "MEASURES",
    "WrinkleOperator",
    "draw_in_field",
    "median_edge_length",
    "part_quality",
    "penetration_field",
    "ply_components",
    "shear_field",
    "wrinkle_field",
]
