"""Part maps: how the parts of a solver's mesh become a trajectory's components.

A solver's output names its parts (LS-DYNA part ids, Abaqus element sets) but not what they
are to the surrogate. A *part map* (YAML or JSON) says so:

.. code-block:: yaml

    parts:                       # every part, in component order
      1: {type: ply, fiber_angle: 0}       # node type: ply, punch or die
      2: {type: ply, fiber_angle: 90}      # fibre angle in degrees (or fiber_file below)
      3: {type: punch, name: punch}        # name: optional (else the solver's part title)
      4: {type: die}
    fiber_reference: [1, 0, 0]   # optional: the 0 degree direction, projected on each ply
    up: [0, 0, 1]                # optional: the side from which angles turn anticlockwise
    fiber_file: fibres.csv       # optional: rows "node_id, fx, fy, fz" (beside the map)
    grippers:                    # optional
      - nodes: [1017, 2017]      # node ids: the gripped node of every ply
        anchor: [-100.0, 0.0, 0.0]
        force: 60.0              # N, constant

:func:`assemble_parts` builds the trajectory from the parts' cells and the nodes' positions
per state, for :mod:`~torch_ampn.data.d3plot_io` and :mod:`~torch_ampn.data.abaqus_io`: one
component per part in the map's order, nodes that no cell uses dropped, the solver's node ids
kept in ``meta["node_ids"]``. Refused in one line naming the file and the field: parts the map
leaves out or does not find, a node shared by two parts, a ply without fibres, a gripper node
that is not on a ply.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError

_TYPES = {"ply": NodeType.PLY, "punch": NodeType.PUNCH, "die": NodeType.DIE}


# ---- the part map -------------------------------------------------------------------------
def load_part_map(path: str | os.PathLike, key: type = int) -> dict[str, Any]:
    """Read a part map (YAML or JSON) and check its fields; returns it with ``path`` added."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such part map")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        message = f"{path}: not a readable YAML/JSON part map ({err})".replace("\n", " ")
        raise TrajectoryFormatError(message) from err
    return check_part_map(spec, str(path), key)


def check_part_map(spec: Any, source: str = "the part map", key: type = int) -> dict[str, Any]:
    """Check a part map given as a dict; returns a normalised copy.

    ``key``: the type of the part keys, ``int`` (d3plot part ids) or ``str`` (Abaqus element sets).
    """
    if not isinstance(spec, Mapping) or not isinstance(spec.get("parts"), Mapping) or not spec["parts"]:
        raise TrajectoryFormatError(f"{source}: field 'parts' must map part ids to {{type: ply|punch|die}}")
    unknown = sorted(set(spec) - {"parts", "fiber_reference", "up", "fiber_file", "grippers", "path"})
    if unknown:
        raise TrajectoryFormatError(f"{source}: unknown fields {unknown}")
    parts = []
    key_type = key
    for name, role in spec["parts"].items():
        try:
            pid = key_type(name)
        except (TypeError, ValueError):
            message = f"{source}: field 'parts': part id {name!r} is not an integer"
            raise TrajectoryFormatError(message) from None
        role = {"type": role} if isinstance(role, str) else role
        if not isinstance(role, Mapping) or role.get("type") not in _TYPES:
            raise TrajectoryFormatError(
                f"{source}: field 'parts.{pid}.type' must be one of {sorted(_TYPES)}, got "
                f"{role.get('type') if isinstance(role, Mapping) else role!r}"
            )
        extra = sorted(set(role) - {"type", "name", "fiber_angle"})
        if extra:
            raise TrajectoryFormatError(f"{source}: field 'parts.{pid}': unknown keys {extra}")
        angle = role.get("fiber_angle")
        if angle is not None and (role["type"] != "ply" or not _is_number(angle)):
            message = f"{source}: field 'parts.{pid}.fiber_angle' must be a number on a ply"
            raise TrajectoryFormatError(message)
        parts.append({"id": pid, "type": role["type"], "name": role.get("name"), "fiber_angle": angle})
    out: dict[str, Any] = {"parts": parts, "path": spec.get("path", source)}
    for key in ("fiber_reference", "up"):
        value = spec.get(key, [1.0, 0.0, 0.0] if key == "fiber_reference" else [0.0, 0.0, 1.0])
        if not _is_vector(value) or math.hypot(*value) == 0:
            raise TrajectoryFormatError(f"{source}: field '{key}' must be a non-zero [x, y, z]")
        out[key] = [float(v) for v in value]
    out["fiber_file"] = spec.get("fiber_file")
    grippers = spec.get("grippers") or []
    if not isinstance(grippers, list):
        raise TrajectoryFormatError(f"{source}: field 'grippers' must be a list")
    for g, grip in enumerate(grippers):
        ok = isinstance(grip, Mapping) and set(grip) == {"nodes", "anchor", "force"}
        ok = ok and isinstance(grip["nodes"], list) and all(isinstance(n, int) for n in grip["nodes"])
        ok = ok and _is_vector(grip["anchor"]) and _is_number(grip["force"]) and grip["force"] >= 0
        if not ok:
            raise TrajectoryFormatError(
                f"{source}: field 'grippers[{g}]' needs nodes (node ids, one per ply), anchor [x, y, z] "
                "and force (N, >= 0)"
            )
    out["grippers"] = [dict(g) for g in grippers]
    return out


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _is_vector(x: Any) -> bool:
    return isinstance(x, (list, tuple)) and len(x) == 3 and all(_is_number(v) for v in x)


# ---- assembly -----------------------------------------------------------------------------
def assemble_parts(
    source: str,
    spec: dict[str, Any],
    part_cells: Mapping[Any, np.ndarray],
    node_ids: np.ndarray,
    pos: np.ndarray,
    time: np.ndarray | None,
    titles: Mapping[Any, str] | None = None,
    cells_field: str = "cells",
) -> Trajectory:
    """The trajectory of a solver's mesh and a checked part map.

    Args:
        source: The solver file (named in errors and ``meta["source"]``).
        spec: The part map (:func:`check_part_map`).
        part_cells: Part key -> its cells ``[E, 4]`` of node indices (triangles repeat their
            last node, or ``[E, 3]``) into ``pos``.
        node_ids: The solver's id of every node ``[N_all]``.
        pos: Node positions per state ``[T+1, N_all, 3]``.
        time: Time of every state ``[T+1]`` (``None``: the state index).
        titles: Part key -> the solver's part name (the default component names).
        cells_field: The solver file's field that holds the cells (named in errors).
    """
    map_source = spec["path"]
    mapped = [p["id"] for p in spec["parts"]]
    found = [k for k, cells in part_cells.items() if len(cells)]
    left = sorted(set(found) - set(mapped), key=str)
    if left:
        raise TrajectoryFormatError(
            f"{map_source}: field 'parts' leaves parts {left} of {source} unassigned (give each a type)"
        )
    missing = sorted(set(mapped) - set(found), key=str)
    if missing:
        raise TrajectoryFormatError(f"{map_source}: field 'parts': parts {missing} have no cells in {source}")
    # nodes: ordered by component (the map's order), then by their index in the solver's file
    count = pos.shape[1]
    owner = np.full(count, -1, dtype=np.int64)
    order, cells = [], []
    for c, part in enumerate(spec["parts"]):
        elems = np.asarray(part_cells[part["id"]], dtype=np.int64)
        nodes = np.unique(elems)
        shared = nodes[owner[nodes] >= 0]
        if shared.size:
            other = spec["parts"][owner[shared[0]]]["id"]
            raise TrajectoryFormatError(
                f"{source}: field '{cells_field}': node id {node_ids[shared[0]]} belongs to "
                f"parts {other} and {part['id']}; each node must belong to one part"
            )
        owner[nodes] = c
        order.append(nodes)
        cells.append(elems)
    order_all = np.concatenate(order)  # [N] old node index of each new node
    new_index = np.full(count, -1, dtype=np.int64)
    new_index[order_all] = np.arange(order_all.size)
    cells_out = [torch.from_numpy(_shell_cells(new_index[e])) for e in cells]
    pos_t = torch.from_numpy(np.asarray(pos, dtype=np.float64)[:, order_all]).float()
    component = torch.from_numpy(np.repeat(np.arange(len(order)), [o.size for o in order]))
    node_type = torch.tensor([int(_TYPES[spec["parts"][c]["type"]]) for c in component.tolist()])
    times = torch.arange(len(pos)) if time is None else torch.as_tensor(np.asarray(time, dtype=np.float32))
    fiber = _fibres(spec, pos_t[0].double(), cells_out, component, node_ids[order_all], map_source)
    grip_nodes, anchor, force = _grippers(spec, node_ids, new_index, component, node_type, map_source)
    titles = titles or {}
    names = [p["name"] or titles.get(p["id"]) or f"part{p['id']}" for p in spec["parts"]]
    traj = Trajectory(
        pos=pos_t,
        time=times.float(),
        cells=cells_out,
        component=component,
        node_type=node_type,
        fiber=fiber.float(),
        names=names,
        gripper_nodes=grip_nodes,
        gripper_anchor=anchor,
        gripper_force=force,
        meta=dict(source=source, node_ids=node_ids[order_all].tolist(), part_ids=mapped),
    )
    traj.validate(source)
    return traj


def _shell_cells(elems: np.ndarray) -> np.ndarray:
    """Shells ``[E, 4]`` as triangles ``[E, 3]`` or quads ``[E, 4]``.

    Triangles repeat their last node; where a part mixes both, every quad is split in two triangles.
    """
    if elems.shape[1] == 3:
        return elems
    tri = elems[:, 2] == elems[:, 3]
    if tri.all():
        return elems[:, :3]
    if not tri.any():
        return elems
    quads = elems[~tri]
    return np.concatenate([elems[tri, :3], quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def node_normals(pos: Tensor, cells: Tensor, up: Tensor) -> Tensor:
    """Unit normals ``[N, 3]`` of the nodes of ``cells`` (area-weighted), turned towards ``up``."""
    tri = cells if cells.size(1) == 3 else torch.cat([cells[:, [0, 1, 2]], cells[:, [0, 2, 3]]])
    a, b, c = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
    face = torch.linalg.cross(b - a, c - a)  # [F, 3], twice the area
    face = torch.where((face @ up < 0)[:, None], -face, face)
    normal = torch.zeros_like(pos).index_add_(0, tri.reshape(-1), face.repeat_interleave(3, 0))
    return normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-30)


def fibres_from_angle(pos: Tensor, cells: Tensor, angle: float, reference: Tensor, up: Tensor) -> Tensor:
    """Fibre directions ``[N, 3]`` at ``angle`` degrees from ``reference`` projected on the ply.

    At each node of ``cells``: the reference direction projected on the tangent plane (normal
    turned towards ``up``), turned by ``angle`` anticlockwise seen from ``up``. A flat ply in
    the xy plane with the defaults gives ``(cos a, sin a, 0)``. Other rows are zero.
    """
    n = node_normals(pos, cells, up)
    t = reference - (n @ reference)[:, None] * n
    t = t / t.norm(dim=1, keepdim=True).clamp_min(1e-30)
    a = math.radians(angle)
    out = math.cos(a) * t + math.sin(a) * torch.linalg.cross(n, t)
    used = torch.zeros(pos.size(0), dtype=torch.bool)
    used[cells.reshape(-1)] = True
    return torch.where(used[:, None], out, torch.zeros_like(out))


def _fibres(spec: dict, pos0: Tensor, cells: list[Tensor], component: Tensor, ids: np.ndarray,
            source: str) -> Tensor:  # fmt: skip
    fiber = torch.zeros_like(pos0)
    given = torch.zeros(pos0.size(0), dtype=torch.bool)
    if spec["fiber_file"] is not None:
        fiber, given = _read_fibre_file(Path(source).parent / spec["fiber_file"], ids, source)
    reference = torch.tensor(spec["fiber_reference"], dtype=torch.float64)
    up = torch.tensor(spec["up"], dtype=torch.float64)
    for c, part in enumerate(spec["parts"]):
        if part["type"] != "ply":
            continue
        mask = component == c
        if part["fiber_angle"] is not None:
            rows = fibres_from_angle(pos0, cells[c], float(part["fiber_angle"]), reference, up)
            fiber[mask] = rows[mask]
        elif not bool(given[mask].all()):
            raise TrajectoryFormatError(
                f"{source}: field 'parts.{part['id']}': a ply needs fiber_angle, or fiber_file rows for all "
                f"its nodes ({int((~given[mask]).sum())} missing)"
            )
    tool = torch.tensor([p["type"] != "ply" for p in spec["parts"]], dtype=torch.bool)[component]
    fiber[tool] = 0.0
    return fiber


def _read_fibre_file(path: Path, ids: np.ndarray, source: str) -> tuple[Tensor, Tensor]:
    if not path.is_file():
        raise FileNotFoundError(f"{source}: field 'fiber_file': {path}: no such file")
    try:
        rows = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
    except ValueError as err:
        raise TrajectoryFormatError(f"{path}: rows must be 'node_id, fx, fy, fz' ({err})") from err
    if rows.shape[1] != 4:
        message = f"{path}: rows must be 'node_id, fx, fy, fz', got {rows.shape[1]} columns"
        raise TrajectoryFormatError(message)
    where = {int(i): k for k, i in enumerate(ids.tolist())}
    fiber = torch.zeros(len(ids), 3, dtype=torch.float64)
    given = torch.zeros(len(ids), dtype=torch.bool)
    for node_id, *direction in rows.tolist():
        k = where.get(int(node_id))
        if k is not None:
            fiber[k] = torch.tensor(direction, dtype=torch.float64)
            given[k] = True
    return fiber, given


def _grippers(spec: dict, node_ids: np.ndarray, new_index: np.ndarray, component: Tensor, node_type: Tensor,
              source: str) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    plies = [c for c, p in enumerate(spec["parts"]) if p["type"] == "ply"]
    where = {int(i): k for k, i in enumerate(node_ids.tolist())}
    rows = []
    for g, grip in enumerate(spec["grippers"]):
        nodes = []
        for node_id in grip["nodes"]:
            k = where.get(node_id, -1)
            k = int(new_index[k]) if k >= 0 else -1
            if k < 0 or node_type[k] != NodeType.PLY:
                raise TrajectoryFormatError(
                    f"{source}: field 'grippers[{g}].nodes': node id {node_id} is not a node of a ply"
                )
            nodes.append(k)
        on = sorted(int(component[k]) for k in nodes)
        if on != plies:
            raise TrajectoryFormatError(
                f"{source}: field 'grippers[{g}].nodes': one node per ply needed (ply parts "
                f"{[spec['parts'][c]['id'] for c in plies]}), got nodes on parts "
                f"{[spec['parts'][c]['id'] for c in on]}"
            )
        rows.append(sorted(nodes, key=lambda k: int(component[k])))
    if not rows:
        return torch.empty(0, max(len(plies), 1), dtype=torch.long), torch.empty(0, 3), torch.empty(0)
    anchor = torch.tensor([g["anchor"] for g in spec["grippers"]], dtype=torch.float32)
    force = torch.tensor([float(g["force"]) for g in spec["grippers"]], dtype=torch.float32)
    return torch.tensor(rows, dtype=torch.long), anchor, force


__all__ = [
    "assemble_parts",
    "check_part_map",
    "fibres_from_angle",
    "load_part_map",
    "node_normals",
]
