"""meshio I/O: export trajectories (true and predicted) for ParaView, import FEM time series.

Exchange format (XDMF time series, or a folder of VTU files, one per saved step):

* mesh: the **initial** node positions and the cells (``triangle`` for plies, ``quad`` for
  tools; any mix of blocks). A cell belongs to the component of its nodes.
* point data, static (read from the first step): ``component`` (int, required),
  ``node_type`` (int, :class:`~torch_ampn.data.NodeType`: 0 ply, 1 punch, 2 die; required),
  ``fiber`` (``[N, 3]``, optional, zero if absent).
* point data, per step: ``displacement`` (``[N, 3]``, from the initial positions, required).
  Exports add ``predicted_displacement`` and ``error`` (norm of the difference) when a
  prediction is given.
* metadata (optional): a JSON file beside the input, ``<stem>.meta.json`` for
  ``<stem>.xdmf`` or ``meta.json`` in a VTU folder, with optional keys ``time`` (one
  value per step; used for VTU series), ``names``
  (component names), ``gripper_nodes`` (``[G][P]`` node indices, one per ply),
  ``gripper_anchor`` (``[G][3]``, mm) and ``gripper_force`` (``[G]``, N). Without it the
  components are named ``component0 ..`` and the trajectory has no grippers.

FEM results from Abaqus (``.odb``) or LS-DYNA (``d3plot``) cannot be read by meshio;
export them to VTU/XDMF first (e.g. Abaqus: ``abaqus python`` with the ODB API or the
"odb2vtk" scripts; LS-DYNA: LS-PrePost "Save as VTK", or ParaView's d3plot reader and
"Save Data" as a VTU series) with the field names above.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import meshio
import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError
from torch_ampn.utils.io import atomic_folder

_CELL_TYPES = {3: "triangle", 4: "quad"}


@contextlib.contextmanager
def _working_directory(path: str | os.PathLike) -> Iterator[None]:
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def _cell_blocks(traj: Trajectory) -> list[tuple[str, np.ndarray]]:
    return [(_CELL_TYPES[c.size(1)], c.numpy()) for c in traj.cells]


def export_xdmf(traj: Trajectory, path: str | os.PathLike, predicted_pos: Tensor | None = None) -> Path:
    """Write ``traj`` (and optionally a predicted rollout) as an XDMF time series for ParaView.

    Point data per step: ``displacement`` (true), and with ``predicted_pos`` ``[T+1, N, 3]``
    also ``predicted_displacement`` and ``error`` (distance between predicted and true
    position, mm); static: ``component``, ``node_type``, ``fiber``. In ParaView, apply
    "Warp By Vector" with ``displacement`` (or ``predicted_displacement``) to see the
    deformed shapes. Written atomically (the ``.xdmf``, its ``.h5`` and ``.meta.json`` files).

    Returns:
        The path of the ``.xdmf`` file.
    """
    path = Path(path)
    if path.suffix != ".xdmf":
        raise ValueError(f"{path}: the file name must end in .xdmf")
    if predicted_pos is not None and tuple(predicted_pos.shape) != tuple(traj.pos.shape):
        raise ValueError(
            f"predicted_pos has shape {list(predicted_pos.shape)}, the trajectory {list(traj.pos.shape)}"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".tmp-xdmf-") as tmp:
        tmp_path = Path(tmp) / path.name
        u = traj.displacement().numpy()
        static = dict(
            component=traj.component.numpy().astype(np.int32),
            node_type=traj.node_type.numpy().astype(np.int32),
            fiber=traj.fiber.numpy(),
        )
        # meshio 5.3 writes the .h5 file into the working directory: write from inside tmp
        with _working_directory(tmp), meshio.xdmf.TimeSeriesWriter(tmp_path.name) as writer:
            writer.write_points_cells(traj.pos[0].numpy(), _cell_blocks(traj))
            for k, t in enumerate(traj.time.tolist()):
                data = dict(static, displacement=u[k])
                if predicted_pos is not None:
                    data["predicted_displacement"] = (predicted_pos[k] - traj.pos[0]).numpy()
                    data["error"] = (predicted_pos[k] - traj.pos[k]).norm(dim=-1).numpy()
                writer.write_data(t, point_data=data)
        # the writer references its HDF5 file by name: move both, the .h5 first
        write_meta_json(traj, tmp_path.with_suffix(".meta.json"))
        h5 = tmp_path.with_suffix(".h5")
        if h5.exists():
            os.replace(h5, path.with_suffix(".h5"))
        os.replace(tmp_path.with_suffix(".meta.json"), path.with_suffix(".meta.json"))
        os.replace(tmp_path, path)
    return path


def _read_meta(sidecar: Path) -> dict:
    """The optional metadata JSON (see the module docstring), ``{}`` if absent."""
    if not sidecar.exists():
        return {}
    try:
        meta = json.loads(sidecar.read_text())
        if not isinstance(meta, dict):
            raise ValueError("expected a JSON object")
        if "gripper_nodes" in meta:
            nodes = torch.tensor(meta["gripper_nodes"], dtype=torch.long)
            meta["gripper_nodes"] = nodes[:, None] if nodes.dim() == 1 else nodes
            meta["gripper_anchor"] = torch.tensor(meta["gripper_anchor"], dtype=torch.float32).reshape(-1, 3)
            meta["gripper_force"] = torch.tensor(meta["gripper_force"], dtype=torch.float32).reshape(-1)
    except (KeyError, ValueError, TypeError, RuntimeError) as err:
        raise TrajectoryFormatError(f"{sidecar}: invalid metadata file ({err})") from err
    return meta


def write_meta_json(traj: Trajectory, path: str | os.PathLike) -> None:
    """Write the metadata sidecar file (names and grippers, see the module docstring) of ``traj``."""
    spec = dict(
        time=traj.time.tolist(),
        names=list(traj.names),
        gripper_nodes=traj.gripper_nodes.tolist(),
        gripper_anchor=traj.gripper_anchor.tolist(),
        gripper_force=traj.gripper_force.tolist(),
    )
    Path(path).write_text(json.dumps(spec))


def _assemble(
    source: str,
    points: np.ndarray,
    cells: list,
    first_point_data: dict,
    times: list[float],
    displacements: list[np.ndarray],
    meta: dict,
) -> Trajectory:
    """Trajectory from the pieces of a time series; errors name ``source`` and the field."""
    for name in ("component", "node_type"):
        if name not in first_point_data:
            raise TrajectoryFormatError(f"{source}: missing point data field {name!r}")
    n = points.shape[0]
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise TrajectoryFormatError(
            f"{source}: field 'points' must have shape [N, 3], got {list(points.shape)}"
        )
    if points.shape[1] == 2:
        points = np.concatenate([points, np.zeros((n, 1))], 1)
    component = torch.as_tensor(np.asarray(first_point_data["component"]).reshape(-1), dtype=torch.long)
    node_type = torch.as_tensor(np.asarray(first_point_data["node_type"]).reshape(-1), dtype=torch.long)
    fiber = np.asarray(first_point_data.get("fiber", np.zeros((n, 3))), dtype=np.float32)
    if len(displacements) < 2:
        raise TrajectoryFormatError(f"{source}: field 'displacement' must be given for at least 2 steps")
    for k, u in enumerate(displacements):
        if u is None:
            raise TrajectoryFormatError(f"{source}: missing point data field 'displacement' at step {k}")
        if u.shape != (n, 3):
            raise TrajectoryFormatError(
                f"{source}: field 'displacement' at step {k} has shape {list(u.shape)}, expected [{n}, 3]"
            )
    pos0 = torch.as_tensor(points, dtype=torch.float32)
    pos = pos0[None] + torch.as_tensor(np.stack(displacements), dtype=torch.float32)
    num_comp = int(component.max()) + 1 if component.numel() else 0
    per_comp: list[list[Tensor]] = [[] for _ in range(num_comp)]
    for block in cells:
        data = torch.as_tensor(np.asarray(block.data), dtype=torch.long)
        if data.size(1) not in (3, 4):
            raise TrajectoryFormatError(
                f"{source}: unsupported cell type {block.type!r} (triangles and quads only)"
            )
        comp = component[data[:, 0]]
        for c in comp.unique().tolist():
            per_comp[c].append(data[comp == c])
    cells_out = []
    for c, blocks in enumerate(per_comp):
        if not blocks:
            raise TrajectoryFormatError(f"{source}: field 'component': component {c} has no cells")
        if len({b.size(1) for b in blocks}) > 1:
            raise TrajectoryFormatError(f"{source}: component {c} mixes triangles and quads")
        cells_out.append(torch.cat(blocks))
    names = list(meta.get("names", [f"component{c}" for c in range(num_comp)]))
    traj = Trajectory(
        pos=pos,
        time=torch.tensor(times, dtype=torch.float32),
        cells=cells_out,
        component=component,
        node_type=node_type,
        fiber=torch.as_tensor(fiber),
        names=names,
        gripper_nodes=meta.get("gripper_nodes", torch.empty(0, 1, dtype=torch.long)),
        gripper_anchor=meta.get("gripper_anchor", torch.empty(0, 3)),
        gripper_force=meta.get("gripper_force", torch.empty(0)),
        meta=dict(source=source),
    )
    traj.validate(source)
    return traj


def read_xdmf(path: str | os.PathLike) -> Trajectory:
    """Read an XDMF time series (as written by :func:`export_xdmf` or an FEM export)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
            points, cells = reader.read_points_cells()
            times, disps, first = [], [], None
            for k in range(reader.num_steps):
                t, point_data, _ = reader.read_data(k)
                first = point_data if first is None else first
                times.append(float(t))
                disps.append(
                    None if "displacement" not in point_data else np.asarray(point_data["displacement"])
                )
    except TrajectoryFormatError:
        raise
    except Exception as err:
        raise TrajectoryFormatError(f"{path}: not a readable XDMF time series ({err})") from err
    if first is None:
        raise TrajectoryFormatError(f"{path}: the time series has no steps")
    meta = _read_meta(path.with_suffix(".meta.json"))
    return _assemble(str(path), points, cells, first, times, disps, meta)


def read_vtu_series(folder: str | os.PathLike) -> Trajectory:
    """Read a folder of VTU files, one per saved step, in file-name order.

    Each file holds the initial points (or the current ones, then ``displacement`` may be
    omitted and is taken as the change of the points) and the same cells; the time of a step
    is taken from ``meta.json``'s ``time`` list if present, else from the field data
    ``time``, else it is the step index.
    """
    folder = Path(folder)
    files = sorted(folder.glob("*.vtu"))
    if not files:
        raise TrajectoryFormatError(f"{folder}: no .vtu files")
    meshes = []
    for f in files:
        try:
            meshes.append(meshio.read(f))
        except Exception as err:
            raise TrajectoryFormatError(f"{f}: not a readable VTU file ({err})") from err
    first = meshes[0]
    times, disps = [], []
    for k, (f, m) in enumerate(zip(files, meshes, strict=True)):
        if m.points.shape != first.points.shape:
            raise TrajectoryFormatError(
                f"{f}: field 'points' has {len(m.points)} nodes, the first file {len(first.points)}"
            )
        if "displacement" in m.point_data:
            disps.append(np.asarray(m.point_data["displacement"]))
        else:
            disps.append(np.asarray(m.points - first.points))
        time = m.field_data.get("time")
        times.append(float(np.asarray(time).reshape(-1)[0]) if time is not None else float(k))
    meta = _read_meta(folder / "meta.json")
    if "time" in meta:
        if len(meta["time"]) != len(files):
            raise TrajectoryFormatError(
                f"{folder / 'meta.json'}: field 'time' has {len(meta['time'])} entries for {len(files)} files"
            )
        times = [float(t) for t in meta["time"]]
    return _assemble(str(folder), first.points, first.cells, first.point_data, times, disps, meta)


def read_time_series(path: str | os.PathLike) -> Trajectory:
    """Read an ``.xdmf`` file or a folder of ``.vtu`` files."""
    path = Path(path)
    if path.is_dir():
        return read_vtu_series(path)
    if path.suffix == ".xdmf":
        return read_xdmf(path)
    raise TrajectoryFormatError(f"{path}: expected an .xdmf file or a folder of .vtu files")


def export_vtu_series(traj: Trajectory, folder: str | os.PathLike) -> Path:
    """Write ``traj`` as one VTU file per step (initial points, ``displacement``) plus ``meta.json``."""
    folder = Path(folder)
    with atomic_folder(folder, prefix=".tmp-vtu-") as tmp:
        u = traj.displacement().numpy()
        width = len(str(traj.num_steps))
        for k, t in enumerate(traj.time.tolist()):
            mesh = meshio.Mesh(
                traj.pos[0].numpy(),
                _cell_blocks(traj),
                point_data=dict(
                    displacement=u[k],
                    component=traj.component.numpy().astype(np.int32),
                    node_type=traj.node_type.numpy().astype(np.int32),
                    fiber=traj.fiber.numpy(),
                ),
                field_data=dict(time=np.array([t])),
            )
            mesh.write(tmp / f"step_{k:0{width}d}.vtu")
        write_meta_json(traj, tmp / "meta.json")
    return folder
