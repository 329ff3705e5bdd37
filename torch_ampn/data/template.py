"""New process settings on one's own part: a template trajectory with other grippers.

A *template* is any trajectory of the part (a solver run converted with ``torch-ampn-data
convert``, or a simulated one): it supplies the mesh, the components, the fibres and the
tools' motion. :func:`template_settings` gives it other gripper settings and returns the
trajectory a surrogate rolls out (plies at rest after the initial state, as placeholders;
``meta["ground_truth"]`` is ``False``), for :func:`~torch_ampn.rollout.rollout`,
:func:`~torch_ampn.rollout.rollout_settings` or ``torch-ampn predict --data.predict_template``.

Where a gripper grips is given either as

* an **edge fraction**: gripper ``g`` slides along the straight boundary edge of the first ply
  on which the template's gripper ``g`` sits, from the edge's corner with the smaller
  coordinates (x, then y, then z; fraction 0) to the other corner (fraction 1), to the
  first-ply node nearest that point (the embedded simulator's convention: on its part the
  result equals :func:`~torch_ampn.sim.process_trajectory`), or
* a **node**: the index (0-based, as in the trajectory file) of a first-ply node.

Either way the needle goes through the stack: in every other ply the node nearest the first
ply's node (initial state) is gripped, and the anchor moves with the gripped node, as the
template's anchor sits relative to its node.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory


def template_settings(
    template: Trajectory,
    gripper_forces: Sequence[float] | Tensor,
    gripper_positions: Sequence[float] | Tensor | None = None,
    gripper_nodes: Sequence[int] | Tensor | None = None,
) -> Trajectory:
    """The template with other gripper settings, ready to roll out.

    Args:
        template: A trajectory of the part (mesh, components, fibres, tool motion, G grippers).
        gripper_forces: Pulling force of each gripper in N, ``[G]``.
        gripper_positions: Edge fraction in ``[0, 1]`` of each gripper, ``[G]`` (see the module).
        gripper_nodes: Or: a first-ply node index of each gripper, ``[G]``.

    Returns:
        A trajectory like ``template`` whose ply positions after step 0 are placeholders.

    Raises:
        ValueError: Where the settings cannot be placed on the template (one line).
    """
    g_count = template.num_grippers
    plies = _plies(template)
    if g_count == 0:
        raise ValueError("the template has no grippers: nothing to set (give a run with its grippers)")
    force = torch.as_tensor(gripper_forces, dtype=torch.float64).reshape(-1)
    if force.numel() != g_count or not bool(torch.isfinite(force).all()) or bool((force < 0).any()):
        raise ValueError(f"gripper_forces: {g_count} finite forces >= 0 N needed, got {force.tolist()}")
    if (gripper_positions is None) == (gripper_nodes is None):
        raise ValueError("give either gripper_positions (edge fractions) or gripper_nodes, one per gripper")
    x0 = template.pos[0].double()
    first = torch.nonzero(template.component == plies[0]).squeeze(1)  # first-ply nodes
    if gripper_nodes is not None:
        bases = [int(k) for k in torch.as_tensor(gripper_nodes).reshape(-1).tolist()]
        if len(bases) != g_count:
            raise ValueError(f"gripper_nodes: {g_count} nodes needed, got {len(bases)}")
        for g, k in enumerate(bases):
            if not (0 <= k < template.num_nodes) or int(template.component[k]) != plies[0]:
                raise ValueError(
                    f"gripper_nodes[{g}]: node {k} is not a node of the first ply "
                    f"({template.names[plies[0]]}, nodes {int(first.min())}..{int(first.max())})"
                )
    else:
        where = torch.as_tensor(gripper_positions, dtype=torch.float64).reshape(-1)
        if where.numel() != g_count or bool(((where < 0) | (where > 1) | ~torch.isfinite(where)).any()):
            raise ValueError(
                f"gripper_positions: {g_count} edge fractions in [0, 1] needed, got {where.tolist()}"
            )
        bases = []
        for g in range(g_count):
            a, b = gripper_edge(template, g)
            point = a + float(where[g]) * (b - a)
            bases.append(int(first[((x0[first] - point) ** 2).sum(1).argmin()]))
    nodes, anchors = [], []
    for g, base in enumerate(bases):
        row = [base]
        for c in plies[1:]:
            ply = torch.nonzero(template.component == c).squeeze(1)
            row.append(int(ply[((x0[ply] - x0[base]) ** 2).sum(1).argmin()]))
        nodes.append(row)
        offset = template.gripper_anchor[g].double() - x0[template.gripper_nodes[g, 0]]
        anchors.append(x0[base] + offset)
    ply_mask = template.node_type == NodeType.PLY
    pos = template.pos.clone()
    pos[1:, ply_mask] = template.pos[0, ply_mask]
    meta = {**template.meta, "ground_truth": False, "template": template.meta.get("source", "template")}
    if gripper_positions is not None:
        meta["gripper_edge_fraction"] = (
            torch.as_tensor(gripper_positions, dtype=torch.float64).reshape(-1).tolist()
        )
    out = dataclasses.replace(
        template,
        pos=pos,
        gripper_nodes=torch.tensor(nodes, dtype=torch.long),
        gripper_anchor=torch.stack(anchors).to(template.gripper_anchor.dtype),
        gripper_force=force.to(template.gripper_force.dtype),
        meta=meta,
        prior=None,
    )
    out.validate("the template with new settings")
    return out


def _plies(template: Trajectory) -> list[int]:
    """The components of ply nodes, in order."""
    plies = sorted({int(c) for c in template.component[template.node_type == NodeType.PLY].tolist()})
    if not plies:
        raise ValueError("the template has no ply nodes")
    return plies


def boundary_loop(cells: Tensor) -> list[int]:
    """The nodes of the outer boundary of a mesh's cells ``[F, 3|4]``, in order along the loop.

    Boundary edges are those of one cell only; the longest closed loop is the outer boundary.
    """
    k = cells.size(1)
    edges = torch.cat([cells[:, [i, (i + 1) % k]] for i in range(k)]).sort(1).values
    unique, counts = torch.unique(edges, dim=0, return_counts=True)
    boundary = unique[counts == 1].tolist()
    nbrs: dict[int, list[int]] = {}
    for a, b in boundary:
        nbrs.setdefault(a, []).append(b)
        nbrs.setdefault(b, []).append(a)
    loops, seen = [], set()
    for start in nbrs:
        if start in seen:
            continue
        loop, prev, node = [start], None, start
        seen.add(start)
        while True:
            nxt = [n for n in nbrs[node] if n != prev and n not in seen]
            if not nxt:
                break
            prev, node = node, nxt[0]
            loop.append(node)
            seen.add(node)
        loops.append(loop)
    return max(loops, key=len)


def gripper_edge(template: Trajectory, g: int, corner_degrees: float = 20.0) -> tuple[Tensor, Tensor]:
    """The corners ``(a, b)`` ``[3]`` of the first ply's straight edge under the template's gripper ``g``.

    ``a`` is fraction 0 (the smaller coordinates: x, then y, then z), ``b`` fraction 1. Corners
    are the boundary nodes where the boundary turns by more than ``corner_degrees``.
    """
    plies = _plies(template)
    x0 = template.pos[0].double()
    loop = boundary_loop(template.cells[plies[0]])
    base = int(template.gripper_nodes[g, 0])
    if base not in loop:
        raise ValueError(
            f"the template's gripper {g} (node {base}) is not on the first ply's outer boundary: "
            "give gripper_nodes instead of edge fractions"
        )
    n = len(loop)
    pts = x0[loop]
    before, after = pts - pts.roll(1, 0), pts.roll(-1, 0) - pts
    cos = (before * after).sum(1) / (before.norm(dim=1) * after.norm(dim=1)).clamp_min(1e-30)
    corner = cos < torch.cos(torch.deg2rad(torch.tensor(corner_degrees, dtype=torch.float64)))
    if int(corner.sum()) < 2:
        raise ValueError("the first ply's boundary has fewer than 2 corners: give gripper_nodes instead")
    i = loop.index(base)
    ends = []
    for step in (1, -1):  # walk to the corner on each side (the gripper's node may itself be one)
        j = i
        while not bool(corner[j % n]):
            j += step
        ends.append(j % n)
    if ends[0] == ends[1]:  # the gripper sits on a corner: take the edge towards the next corner
        j = i + 1
        while not bool(corner[j % n]):
            j += 1
        ends[1] = j % n
    a, b = pts[ends[0]], pts[ends[1]]
    scale = float((pts.max(0).values - pts.min(0).values).max()) or 1.0
    if tuple(round(v / scale, 6) for v in b.tolist()) < tuple(round(v / scale, 6) for v in a.tolist()):
        a, b = b, a
    return a, b


__all__ = ["boundary_loop", "gripper_edge", "template_settings"]
