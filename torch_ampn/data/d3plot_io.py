"""LS-DYNA ``d3plot`` exchange through lasso-python (the ``d3plot`` extra).

A d3plot holds the mesh (nodes, shell elements and the part of each element) and, per saved
state, the nodes' current coordinates (lasso's ``node_displacement``). What it does not hold
(which part is a ply, punch or die, the fibres, the grippers), a part map gives
(:mod:`torch_ampn.data.part_map`; its part keys are the d3plot's part ids).

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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.part_map import _TYPES, assemble_parts, check_part_map, load_part_map
from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError
from torch_ampn.utils.io import atomic_folder

PART_MAP_NAME = "parts.yaml"


def _lasso() -> Any:
    try:
        from lasso.dyna import ArrayType, D3plot
    except ImportError as err:  # pragma: no cover - the extra is installed in CI
        raise ImportError(
            "reading and writing d3plot files needs lasso-python: pip install 'torch-ampn[d3plot]'"
        ) from err
    return D3plot, ArrayType


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
    part_ids = _part_ids(path, arrays, A)
    shell_index = np.asarray(arrays.get(A.element_shell_part_indexes, np.empty(0)), dtype=np.int64)
    if shell_index.shape != (shells.shape[0],) or shell_index.min(initial=0) < 0:
        raise TrajectoryFormatError(
            f"{path}: field 'element_shell_part_indexes': {shell_index.shape[0]} part indexes for "
            f"{shells.shape[0]} shells"
        )
    if shell_index.max(initial=-1) >= part_ids.size:
        raise TrajectoryFormatError(
            f"{path}: field 'element_shell_part_indexes': part index {int(shell_index.max())} but "
            f"{part_ids.size} parts"
        )
    shell_part = part_ids[shell_index]  # [E]
    node_ids = np.asarray(arrays.get(A.node_ids, np.arange(1, disp.shape[1] + 1)), dtype=np.int64)
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
    part_cells = {int(p): shells[shell_part == p] for p in np.unique(shell_part)}
    times = arrays.get(A.global_timesteps)
    return assemble_parts(
        str(path),
        spec,
        part_cells,
        node_ids,
        pos,
        times,
        _part_titles(arrays, A),
        "element_shell_node_indexes",
    )


def _part_ids(path: str | os.PathLike, arrays: Mapping, A: Any) -> np.ndarray:
    """The parts' ids in their internal order ``[P]``: lasso's ``part_ids``, else those of the titles section.

    A d3plot whose parts come with titles only gives lasso ``part_titles_ids`` and no ``part_ids``;
    both list the parts in the order that ``element_shell_part_indexes`` counts.
    """
    for field in (A.part_ids, A.part_titles_ids):
        ids = arrays.get(field)
        if ids is not None and np.size(ids):
            return np.asarray(ids, dtype=np.int64).reshape(-1)
    raise TrajectoryFormatError(
        f"{path}: field 'part_ids': the d3plot names no part ids (neither 'part_ids' nor 'part_titles_ids')"
    )


def _part_titles(arrays: Mapping, A: Any) -> dict[int, str]:
    ids, titles = arrays.get(A.part_titles_ids), arrays.get(A.part_titles)
    if ids is None or titles is None:
        return {}
    return {int(i): bytes(t).decode(errors="replace").strip() for i, t in zip(ids, titles, strict=False)}


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
    with atomic_folder(folder, prefix=".tmp-d3plot-") as tmp:
        plot.write_d3plot(str(tmp / "d3plot"))
        (tmp / PART_MAP_NAME).write_text(yaml.safe_dump(spec, sort_keys=False))
        if fibre_rows is not None:
            np.savetxt(tmp / "fibres.csv", fibre_rows, delimiter=",", fmt=["%d", "%.9g", "%.9g", "%.9g"],
                       header="node_id, fx, fy, fz")  # fmt: skip
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


__all__ = ["PART_MAP_NAME", "read_d3plot", "write_d3plot"]
