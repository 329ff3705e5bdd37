"""Abaqus runs: a flat input deck (``.inp``, through meshio) and a displacement table from the ODB.

The ODB can only be read inside Abaqus's own Python, so an Abaqus run comes in two files:

* the input deck ``forming.inp``: nodes, shell elements (``S3``/``S4``/``M3D3``/``M3D4``/
  ``R3D3``/``R3D4``, ...) and one element set (``*Elset``) per ply and tool. Flat decks only:
  a deck with parts and instances (``*Instance``) is refused; Abaqus/CAE writes a flat one with
  "Model > Edit Attributes > Do not use parts and assemblies in input files";
* the displacement table ``forming.npz``, written by ``abaqus python
  scripts/abaqus_odb_export.py forming.odb``: ``node_labels [N]`` (the deck's node numbers),
  ``time [T+1]`` and ``u [T+1, N, 3]`` (nodal ``U`` of every saved frame, mm).

:func:`read_abaqus` joins them with a part map (:mod:`torch_ampn.data.part_map`) whose part
keys are the deck's element set names. Line and point elements (connectors, springs,
reference nodes) are ignored; solid or higher-order elements are refused.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from torch_ampn.data.part_map import assemble_parts, check_part_map, load_part_map
from torch_ampn.data.trajectory import Trajectory, TrajectoryFormatError

_SHELLS = {"triangle": 3, "quad": 4}
_IGNORED = {"line", "line3", "vertex"}
_NODE_KEYWORD = re.compile(r"^\*node\s*(,|$)", re.IGNORECASE)


def _node_blocks(text: str) -> tuple[list[str], list[str]]:
    """``(node data lines of every *Node block, the other lines)``, comments dropped."""
    nodes, other, inside = [], [], False
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("**") or not stripped:
            continue
        if stripped.startswith("*"):
            inside = bool(_NODE_KEYWORD.match(stripped))
            if not inside:
                other.append(line)
            elif not nodes and "*Node" not in other:
                other.append("*Node")  # where the first block was: every node goes there
            continue
        (nodes if inside else other).append(line)
    return nodes, other


def node_labels(inp: str | os.PathLike) -> np.ndarray:
    """The node numbers of a flat deck's ``*Node`` blocks, in file order ``[N]``."""
    nodes, _ = _node_blocks(Path(inp).read_text(encoding="utf-8", errors="replace"))
    return np.asarray([int(line.split(",")[0]) for line in nodes], dtype=np.int64)


def merged_node_blocks(text: str) -> str:
    """The deck with all ``*Node`` blocks as one (meshio 5.3 keeps only the last block it reads)."""
    nodes, other = _node_blocks(text)
    at = other.index("*Node") if "*Node" in other else 0
    return "\n".join([*other[: at + 1], *nodes, *other[at + 1 :]]) + "\n"


def read_abaqus(
    inp: str | os.PathLike,
    displacements: str | os.PathLike | None = None,
    part_map: str | os.PathLike | Mapping | None = None,
) -> Trajectory:
    """Read a flat Abaqus deck and its displacement table as a trajectory.

    Args:
        inp: The input deck (``.inp``).
        displacements: The ODB export's table (default: ``<deck>.npz`` beside the deck).
        part_map: The part map, keyed by element set names (default ``parts.yaml`` beside the deck).

    Returns:
        One component per mapped element set, in the map's order; ``meta["node_ids"]``: node labels.
    """
    import meshio

    inp = Path(inp)
    if not inp.is_file():
        raise FileNotFoundError(f"{inp}: no such input deck")
    table = Path(displacements) if displacements is not None else inp.with_suffix(".npz")
    if not table.is_file():
        raise FileNotFoundError(
            f"{table}: no such displacement table (write it with: abaqus python "
            "scripts/abaqus_odb_export.py RUN.odb)"
        )
    part_map = inp.parent / "parts.yaml" if part_map is None else part_map
    if isinstance(part_map, Mapping):
        spec = check_part_map(part_map, "the part map", key=str)
    else:
        spec = load_part_map(part_map, key=str)
    text = inp.read_text(encoding="utf-8", errors="replace")
    if re.search(r"^\*instance", text, re.IGNORECASE | re.MULTILINE):
        raise TrajectoryFormatError(
            f"{inp}: field '*Instance': decks with parts and assemblies are not supported; write a flat "
            "deck (Model > Edit Attributes > Do not use parts and assemblies in input files)"
        )
    try:
        with tempfile.TemporaryDirectory() as tmp:  # meshio reads a path: the merged deck goes there
            merged = Path(tmp) / inp.name
            merged.write_text(merged_node_blocks(text))
            mesh = meshio.read(merged, file_format="abaqus")
    except Exception as err:
        raise TrajectoryFormatError(
            f"{inp}: not a readable Abaqus input deck ({err})".replace("\n", " ")
        ) from err
    labels = node_labels(inp)
    if labels.size != len(mesh.points):
        raise TrajectoryFormatError(
            f"{inp}: field '*Node': {labels.size} node lines for {len(mesh.points)} nodes meshio read"
        )
    for block in mesh.cells:
        if block.type not in _SHELLS and block.type not in _IGNORED and len(block.data):
            raise TrajectoryFormatError(
                f"{inp}: field '*Element': {len(block.data)} elements of type {block.type!r}; only "
                "linear shells (triangles and quads) are supported"
            )
    part_cells, covered = {}, [np.zeros(len(b.data), dtype=bool) for b in mesh.cells]
    for part in spec["parts"]:
        sets = mesh.cell_sets.get(part["id"]) or mesh.cell_sets.get(str(part["id"]).upper())
        rows = []
        for k, (block, index) in enumerate(zip(mesh.cells, sets or [], strict=False)):
            if block.type not in _SHELLS or not len(index):
                continue
            data = np.asarray(block.data, dtype=np.int64)[np.asarray(index, dtype=np.int64)]
            rows.append(np.concatenate([data, data[:, 2:3]], 1) if data.shape[1] == 3 else data)
            covered[k][np.asarray(index, dtype=np.int64)] = True
        part_cells[part["id"]] = np.concatenate(rows) if rows else np.empty((0, 4), dtype=np.int64)
    left = sum(int((~c).sum()) for c, b in zip(covered, mesh.cells, strict=True) if b.type in _SHELLS)
    if left:
        names = sorted(n for n in mesh.cell_sets if not n.startswith("_"))
        raise TrajectoryFormatError(
            f"{spec['path']}: field 'parts' leaves {left} shell elements of {inp} in no mapped element set "
            f"(element sets of the deck: {names})"
        )
    u, time = _read_table(table, labels)
    pos = np.asarray(mesh.points, dtype=np.float64)[None] + u
    return assemble_parts(str(inp), spec, part_cells, labels, pos, time, cells_field="*Elset")


def _read_table(path: Path, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``u [T+1, N, 3]`` in the deck's node order and ``time [T+1]`` from the ODB export's table."""
    try:
        data = np.load(path)
    except Exception as err:
        raise TrajectoryFormatError(f"{path}: not a readable .npz displacement table ({err})") from err
    for field in ("node_labels", "time", "u"):
        if field not in data:
            raise TrajectoryFormatError(f"{path}: field '{field}' is missing (node_labels, time, u needed)")
    table_labels, time, u = (np.asarray(data[f]) for f in ("node_labels", "time", "u"))
    if u.ndim != 3 or u.shape[1:] != (table_labels.size, 3) or u.shape[0] != time.size or time.size < 2:
        raise TrajectoryFormatError(
            f"{path}: field 'u' has shape {list(u.shape)}; expected [T+1 >= 2, {table_labels.size}, 3] "
            f"with T+1 = {time.size} times"
        )
    row = {int(label): k for k, label in enumerate(table_labels.tolist())}
    missing = [int(label) for label in labels.tolist() if int(label) not in row]
    if missing:
        raise TrajectoryFormatError(
            f"{path}: field 'node_labels': {len(missing)} nodes of the deck have no displacement "
            f"(first: {missing[:3]})"
        )
    index = np.array([row[int(label)] for label in labels.tolist()], dtype=np.int64)
    return np.asarray(u, dtype=np.float64)[:, index], np.asarray(time, dtype=np.float64)


__all__ = ["merged_node_blocks", "node_labels", "read_abaqus"]
