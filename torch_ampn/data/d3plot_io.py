"""LS-DYNA ``d3plot`` exchange through lasso-python (the ``d3plot`` extra).

A d3plot holds the mesh (nodes, shell elements and the part of each element) and, per saved
state, the nodes' current coordinates (lasso's ``node_displacement``). What it does not hold,
a small *part map* (YAML or JSON) gives:

.. code-block:: yaml

    parts:                       # every part of the d3plot, in component order
      1: {type: ply, fiber_angle: 0}       # node type: ply, punch or die
      2: {type: ply, fiber_angle: 90}      # fibre angle in degrees (or fiber_file below)
      3: {type: punch, name: punch}        # name: optional (else the d3plot's part title)
      4: {type: die}
    fiber_reference: [1, 0, 0]   # optional: the 0 degree direction, projected on each ply
    up: [0, 0, 1]                # optional: the side from which angles turn anticlockwise
    fiber_file: fibres.csv       # optional: rows "node_id, fx, fy, fz" (beside the map)
    grippers:                    # optional
      - nodes: [1017, 2017]      # d3plot node ids: the gripped node of every ply
        anchor: [-100.0, 0.0, 0.0]
        force: 60.0              # N, constant

:func:`read_d3plot` turns a d3plot and its map into a :class:`~torch_ampn.data.Trajectory`
(components in the map's order, nodes that no shell uses dropped, the d3plot's node and
part ids kept in ``meta``); :func:`write_d3plot` writes a trajectory (and optionally a
predicted rollout in its place) as a d3plot with lasso's writer, plus the part map that reads
it back. Refused, in one line naming the file and the field: a d3plot without states, solid
or thick-shell elements, deleted elements, adaptive remeshing, parts the map leaves out, a
node shared by two parts, a gripper node that is not on a ply.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError

_TYPES = {"ply": NodeType.PLY, "punch": NodeType.PUNCH, "die": NodeType.DIE}
PART_MAP_NAME = "parts.yaml"


def _lasso() -> Any:
    try:
        from lasso.dyna import ArrayType, D3plot
    except ImportError as err:  # pragma: no cover - the extra is installed in CI
        raise ImportError(
            "reading and writing d3plot files needs lasso-python: pip install 'torch-ampn[d3plot]'"
        ) from err
    return D3plot, ArrayType


# ---- the part map ---------------------------------------------------------------------------
def load_part_map(path: str | os.PathLike) -> dict[str, Any]:
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
    return check_part_map(spec, str(path))


def check_part_map(spec: Any, source: str = "the part map") -> dict[str, Any]:
    """Check a part map given as a dict (see the module docstring); returns a normalised copy."""
    if not isinstance(spec, Mapping) or not isinstance(spec.get("parts"), Mapping) or not spec["parts"]:
        raise TrajectoryFormatError(f"{source}: field 'parts' must map part ids to {{type: ply|punch|die}}")
    unknown = sorted(set(spec) - {"parts", "fiber_reference", "up", "fiber_file", "grippers", "path"})
    if unknown:
        raise TrajectoryFormatError(f"{source}: unknown fields {unknown}")
    parts = []
    for key, role in spec["parts"].items():
        try:
            pid = int(key)
        except (TypeError, ValueError):
            message = f"{source}: field 'parts': part id {key!r} is not an integer"
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


# ---- reading --------------------------------------------------------------------------------
def read_d3plot(path: str | os.PathLike, part_map: str | os.PathLike | Mapping | None = None) -> Trajectory:
    """Read an LS-DYNA d3plot (and its part map) as a trajectory.

    Args:
        path: The first file of the d3plot series (``run/d3plot``; ``d3plot01`` .. are found).
        part_map: The part map (a path, or a dict of the same fields); default ``parts.yaml``
            beside the d3plot.

    Returns:
        The trajectory: ``pos [T+1, N, 3]`` of the N nodes that shell elements use, one component
        per part in the map's order; ``meta["node_ids"]`` and ``meta["part_ids"]`` hold the d3plot's ids.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such d3plot file")
    if part_map is None:
        part_map = path.parent / PART_MAP_NAME
    if isinstance(part_map, Mapping):
        spec = check_part_map(part_map, "the part map")
    else:
        spec = load_part_map(part_map)
    D3plot, A = _lasso()
    try:
        plot = D3plot(str(path))
    except Exception as err:
        raise TrajectoryFormatError(f"{path}: not a readable d3plot ({err})".replace("\n", " ")) from err
    arrays, header = plot.arrays, plot.header
    for field, count in [
        ("element_solid_node_indexes", header.n_solids),
        ("element_tshell_node_indexes", header.n_thick_shells),
    ]:
        if count:
            raise TrajectoryFormatError(
                f"{path}: field '{field}': {count} solid or thick-shell elements; only shells are supported"
            )
    if header.n_adapted_element_pairs:
        raise TrajectoryFormatError(
            f"{path}: field 'nadapt': adaptive remeshing ({header.n_adapted_element_pairs} element pairs) "
            "is not supported"
        )
    disp = arrays.get(A.node_displacement)
    if disp is None or disp.ndim != 3 or disp.shape[0] < 2:
        states = 0 if disp is None else disp.shape[0]
        raise TrajectoryFormatError(
            f"{path}: field 'node_displacement': the d3plot holds nodal displacements for {states} states, "
            "at least 2 needed (write displacements in every state)"
        )
    alive = arrays.get(A.element_shell_is_alive)
    if alive is not None and np.any(np.asarray(alive) == 0):
        dead = int(np.any(np.asarray(alive) == 0, axis=0).sum())
        raise TrajectoryFormatError(
            f"{path}: field 'element_shell_is_alive': {dead} shell elements are deleted during the run; "
            "element erosion is not supported"
        )
    shells = np.asarray(arrays.get(A.element_shell_node_indexes, np.empty((0, 4), np.int32)), dtype=np.int64)
    if shells.size == 0:
        raise TrajectoryFormatError(f"{path}: field 'element_shell_node_indexes': the d3plot has no shells")
    part_ids = np.asarray(arrays[A.part_ids], dtype=np.int64)
    shell_part = part_ids[np.asarray(arrays[A.element_shell_part_indexes], dtype=np.int64)]  # [E]
    node_ids = np.asarray(arrays.get(A.node_ids, np.arange(1, disp.shape[1] + 1)), dtype=np.int64)
    titles = _part_titles(arrays, A)

    map_source = spec["path"]
    mapped = [p["id"] for p in spec["parts"]]
    used_parts = sorted(set(shell_part.tolist()))
    left = sorted(set(used_parts) - set(mapped))
    if left:
        raise TrajectoryFormatError(
            f"{map_source}: field 'parts' leaves parts {left} of {path} unassigned (give each a type)"
        )
    missing = sorted(set(mapped) - set(used_parts))
    if missing:
        raise TrajectoryFormatError(f"{map_source}: field 'parts': parts {missing} have no shells in {path}")

    # nodes: ordered by component (the map's order), then by their d3plot index
    owner = np.full(disp.shape[1], -1, dtype=np.int64)
    order, cells = [], []
    for c, part in enumerate(spec["parts"]):
        elems = shells[shell_part == part["id"]]
        nodes = np.unique(elems)
        shared = nodes[owner[nodes] >= 0]
        if shared.size:
            other = spec["parts"][owner[shared[0]]]["id"]
            raise TrajectoryFormatError(
                f"{path}: field 'element_shell_node_indexes': node id {node_ids[shared[0]]} belongs to "
                f"parts {other} and {part['id']}; each node must belong to one part"
            )
        owner[nodes] = c
        order.append(nodes)
        cells.append(elems)
    order_all = np.concatenate(order)  # [N] old node index of each new node
    new_index = np.full(disp.shape[1], -1, dtype=np.int64)
    new_index[order_all] = np.arange(order_all.size)
    cells_out = [torch.from_numpy(_shell_cells(new_index[e])) for e in cells]

    coords = np.asarray(arrays[A.node_coordinates], dtype=np.float64)
    states = np.asarray(disp, dtype=np.float64)
    extent = float(np.ptp(coords, axis=0).max()) or 1.0
    if np.abs(states[0] - coords).max() <= 1e-4 * extent:
        pos = states  # lasso's node_displacement: the current coordinates (what LS-DYNA writes)
    elif np.abs(states[0]).max() <= 1e-4 * extent:
        pos = coords[None] + states  # displacements from the initial coordinates
    else:
        raise TrajectoryFormatError(
            f"{path}: field 'node_displacement': the first state is neither the initial coordinates nor "
            "zero; save the initial state as the first"
        )
    pos_t = torch.from_numpy(pos[:, order_all]).float()
    component = torch.from_numpy(np.repeat(np.arange(len(order)), [o.size for o in order]))
    node_type = torch.tensor([int(_TYPES[spec["parts"][c]["type"]]) for c in component.tolist()])
    times = arrays.get(A.global_timesteps)
    time = torch.arange(len(pos)) if times is None else torch.as_tensor(np.asarray(times, dtype=np.float32))
    fiber = _fibres(spec, pos_t[0].double(), cells_out, component, node_ids[order_all], map_source)
    grip_nodes, anchor, force = _grippers(spec, node_ids, new_index, component, node_type, map_source)
    names = [p["name"] or titles.get(p["id"]) or f"part{p['id']}" for p in spec["parts"]]
    traj = Trajectory(
        pos=pos_t,
        time=time.float(),
        cells=cells_out,
        component=component,
        node_type=node_type,
        fiber=fiber.float(),
        names=names,
        gripper_nodes=grip_nodes,
        gripper_anchor=anchor,
        gripper_force=force,
        meta=dict(source=str(path), node_ids=node_ids[order_all].tolist(), part_ids=mapped),
    )
    traj.validate(str(path))
    return traj


def _part_titles(arrays: Mapping, A: Any) -> dict[int, str]:
    ids, titles = arrays.get(A.part_titles_ids), arrays.get(A.part_titles)
    if ids is None or titles is None:
        return {}
    return {int(i): bytes(t).decode(errors="replace").strip() for i, t in zip(ids, titles, strict=False)}


def _shell_cells(elems: np.ndarray) -> np.ndarray:
    """Shells ``[E, 4]`` as triangles ``[E, 3]`` or quads ``[E, 4]``.

    Triangles repeat their last node; where a part mixes both, every quad is split in two triangles.
    """
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


# ---- writing --------------------------------------------------------------------------------
def write_d3plot(traj: Trajectory, folder: str | os.PathLike, predicted_pos: Tensor | None = None) -> Path:
    """Write ``traj`` as ``folder/d3plot`` (lasso's writer) with the part map that reads it back.

    Part ``c + 1`` is component ``c`` (titled with its name), node ``k + 1`` node ``k``;
    triangles are shells that repeat their last node. The states hold the current coordinates:
    ``traj.pos``, or ``predicted_pos`` ``[T+1, N, 3]`` (a surrogate's rollout, to open in
    LS-PrePost). ``folder/parts.yaml`` gives each part its type and fibre angle where a ply's
    fibres are one in-plane direction turned from x (else ``fibres.csv`` holds every node's
    fibre) and the grippers. The folder is written whole or not at all.

    Returns:
        The path of the ``d3plot`` file.
    """
    import yaml

    D3plot, A = _lasso()
    pos = traj.pos if predicted_pos is None else predicted_pos
    if tuple(pos.shape) != tuple(traj.pos.shape):
        raise ValueError(f"predicted_pos has shape {list(pos.shape)}, the trajectory {list(traj.pos.shape)}")
    folder = Path(folder)
    if folder.exists():
        foreign = [f.name for f in folder.iterdir() if not _written_here(f.name)] if folder.is_dir() else [""]
        if foreign:
            raise ValueError(f"{folder}: exists and holds other files ({foreign[:3]}); give a new folder")
    folder.parent.mkdir(parents=True, exist_ok=True)
    plot = D3plot()
    n = traj.num_nodes
    shells = [torch.cat([c, c[:, 2:3]], 1) if c.size(1) == 3 else c for c in traj.cells]
    plot.arrays[A.node_coordinates] = traj.pos[0].numpy().astype(np.float32)
    plot.arrays[A.node_ids] = np.arange(1, n + 1, dtype=np.int32)
    plot.arrays[A.node_displacement] = pos.detach().cpu().numpy().astype(np.float32)
    plot.arrays[A.global_timesteps] = traj.time.numpy().astype(np.float32)
    plot.arrays[A.element_shell_node_indexes] = torch.cat(shells).numpy().astype(np.int32)
    plot.arrays[A.element_shell_part_indexes] = np.repeat(
        np.arange(len(shells), dtype=np.int32), [s.size(0) for s in shells]
    )
    plot.arrays[A.element_shell_ids] = np.arange(1, sum(s.size(0) for s in shells) + 1, dtype=np.int32)
    part_ids = np.arange(1, traj.num_components + 1, dtype=np.int32)
    plot.arrays[A.part_ids] = part_ids
    plot.arrays[A.part_titles_ids] = part_ids
    plot.arrays[A.part_titles] = np.array([name.encode()[:72] for name in traj.names])
    spec, fibre_rows = _part_map_of(traj)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=".tmp-d3plot-"))
    try:
        plot.write_d3plot(str(tmp / "d3plot"))
        (tmp / PART_MAP_NAME).write_text(yaml.safe_dump(spec, sort_keys=False))
        if fibre_rows is not None:
            np.savetxt(tmp / "fibres.csv", fibre_rows, delimiter=",", fmt=["%d", "%.9g", "%.9g", "%.9g"],
                       header="node_id, fx, fy, fz")  # fmt: skip
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder / "d3plot"


def _written_here(name: str) -> bool:
    """A file :func:`write_d3plot` writes (so that a folder of them may be replaced)."""
    return name.startswith("d3plot") or name in (PART_MAP_NAME, "fibres.csv")


def _part_map_of(traj: Trajectory) -> tuple[dict[str, Any], np.ndarray | None]:
    """The part map of :func:`write_d3plot`: fibre angles where a ply's fibres allow one, else a CSV."""
    kind = {int(v): k for k, v in _TYPES.items()}
    parts: dict[int, dict[str, Any]] = {}
    by_angle = True
    for c in range(traj.num_components):
        mask = traj.component == c
        role: dict[str, Any] = {"type": kind[int(traj.node_type[mask][0])], "name": traj.names[c]}
        if role["type"] == "ply":
            f = traj.fiber[mask].double()
            flat = bool((f[:, 2].abs() < 1e-6).all()) and bool((f - f[0]).abs().max() < 1e-6)
            pos0 = traj.pos[0, mask].double()
            flat = flat and float(np.ptp(pos0[:, 2].numpy())) < 1e-6
            if flat:
                role["fiber_angle"] = round(math.degrees(math.atan2(float(f[0, 1]), float(f[0, 0]))), 9)
            by_angle = by_angle and flat
        parts[c + 1] = role
    spec: dict[str, Any] = {"parts": parts}
    rows = None
    if not by_angle:
        for role in parts.values():
            role.pop("fiber_angle", None)
        spec["fiber_file"] = "fibres.csv"
        ply = traj.ply_mask
        ids = torch.nonzero(ply).squeeze(1)
        rows = np.column_stack([ids.numpy() + 1, traj.fiber[ply].double().numpy()])
    if traj.num_grippers:
        spec["grippers"] = [
            {
                "nodes": (traj.gripper_nodes[g] + 1).tolist(),
                "anchor": traj.gripper_anchor[g].tolist(),
                "force": float(traj.gripper_force[g]),
            }  # fmt: skip
            for g in range(traj.num_grippers)
        ]
    return spec, rows


__all__ = [
    "PART_MAP_NAME",
    "check_part_map",
    "fibres_from_angle",
    "load_part_map",
    "node_normals",
    "read_d3plot",
    "write_d3plot",
]
