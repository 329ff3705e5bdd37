"""Small triangle/quad mesh builders for tests, benchmarks and the simulator.

All builders return plain tensors: node positions ``pos`` of shape ``[N, 3]`` and cells
of shape ``[F, 3]`` (triangles) or ``[F, 4]`` (quads, counter-clockwise). Several
components are merged into one :class:`MultiComponentMesh` whose graph is the disjoint
union of the component meshes, as the AMPN hierarchy expects.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType


def rectangle_mesh(
    nx: int,
    ny: int,
    size: tuple[float, float] = (1.0, 1.0),
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    cell_type: str = "triangle",
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor]:
    """Structured mesh of the rectangle ``origin + [0, size[0]] x [0, size[1]]`` in the e1-e2 plane.

    Args:
        nx: Number of cells along e1 (at least 1).
        ny: Number of cells along e2 (at least 1).
        size: Edge lengths of the rectangle along e1 and e2.
        origin: Position of the corner with the smallest coordinates.
        cell_type: ``"triangle"`` (each grid square split into two triangles along
            alternating diagonals, ``2 * nx * ny`` cells) or ``"quad"`` (``nx * ny`` cells).
        dtype: Floating point type of the positions.

    Returns:
        ``(pos, cells)``: ``pos`` of shape ``[(nx + 1) * (ny + 1), 3]``, node ``i + j * (nx + 1)``
        at grid point ``(i, j)``; ``cells`` of shape ``[F, 3]`` or ``[F, 4]`` (long).
    """
    if nx < 1 or ny < 1:
        raise ValueError(f"rectangle_mesh needs nx >= 1 and ny >= 1, got nx={nx}, ny={ny}")
    if cell_type not in ("triangle", "quad"):
        raise ValueError(f"cell_type must be 'triangle' or 'quad', got {cell_type!r}")
    xs = torch.linspace(0.0, float(size[0]), nx + 1, dtype=dtype) + origin[0]
    ys = torch.linspace(0.0, float(size[1]), ny + 1, dtype=dtype) + origin[1]
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")  # [ny+1, nx+1]
    pos = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full_like(gx.reshape(-1), origin[2])], 1)

    i = torch.arange(nx).repeat(ny)  # [nx*ny]
    j = torch.arange(ny).repeat_interleave(nx)
    n00 = i + j * (nx + 1)
    n10, n01, n11 = n00 + 1, n00 + nx + 1, n00 + nx + 2
    if cell_type == "quad":
        return pos, torch.stack([n00, n10, n11, n01], 1)
    # Alternate the diagonal in a checkerboard so that the mesh has no preferred direction.
    flip = ((i + j) % 2).bool()
    tri_a = torch.where(flip[:, None], torch.stack([n00, n10, n01], 1), torch.stack([n00, n10, n11], 1))
    tri_b = torch.where(flip[:, None], torch.stack([n10, n11, n01], 1), torch.stack([n00, n11, n01], 1))
    cells = torch.stack([tri_a, tri_b], 1).reshape(-1, 3)
    return pos, cells


def cells_to_edge_index(cells: Tensor, num_nodes: int | None = None) -> Tensor:
    """Undirected mesh edges of triangle or quad cells.

    Args:
        cells: ``[F, 3]`` triangles or ``[F, 4]`` quads (long). Quads contribute their four
            boundary edges, not their diagonals.
        num_nodes: Number of nodes, used only to validate the indices.

    Returns:
        ``LongTensor[2, E]`` with both directions of every edge, without duplicates and
        self-loops, sorted by (source, target).
    """
    if cells.dim() != 2 or cells.size(1) not in (3, 4):
        raise ValueError(f"cells must have shape [F, 3] or [F, 4], got {list(cells.shape)}")
    if cells.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"cells must be an integer tensor, got {cells.dtype}")
    cells = cells.long()
    if num_nodes is not None and cells.numel() > 0 and int(cells.max()) >= num_nodes:
        raise ValueError(f"cells reference node {int(cells.max())} but num_nodes={num_nodes}")
    src = cells.reshape(-1)
    dst = cells.roll(-1, dims=1).reshape(-1)
    ei = torch.cat([torch.stack([src, dst]), torch.stack([dst, src])], 1)
    ei = ei[:, ei[0] != ei[1]]
    return torch.unique(ei, dim=1)


@dataclass
class MultiComponentMesh:
    """Several meshes (plies, punch, die, ...) merged into one graph with disjoint blocks.

    Attributes:
        pos: Node positions, ``[N, 3]``.
        cells: One cell tensor per component, ``[F_c, 3 | 4]`` with global node indices.
        component: Component id of every node, ``[N]`` (long), ``0 .. C-1``.
        node_type: :class:`NodeType` of every node, ``[N]`` (long).
        names: Name of every component.
    """

    pos: Tensor
    cells: list[Tensor]
    component: Tensor
    node_type: Tensor
    names: list[str]

    @property
    def num_nodes(self) -> int:
        """Total number of nodes ``N``."""
        return self.pos.size(0)

    @property
    def num_components(self) -> int:
        """Number of components ``C``."""
        return len(self.cells)

    def edge_index(self) -> Tensor:
        """Undirected mesh edges of all components, ``LongTensor[2, E]``, both directions."""
        return torch.cat([cells_to_edge_index(c, self.num_nodes) for c in self.cells], 1)

    @staticmethod
    def merge(
        parts: Sequence[tuple[str, Tensor, Tensor, int]],
    ) -> MultiComponentMesh:
        """Merge ``(name, pos [N_c, 3], cells [F_c, k], node_type)`` parts into one mesh.

        Component ``c`` gets the ``c``-th part's nodes, numbered after those of the parts before it.
        """
        if len(parts) == 0:
            raise ValueError("MultiComponentMesh.merge needs at least one part")
        pos, cells, comp, types, names, offset = [], [], [], [], [], 0
        for c, (name, p, f, t) in enumerate(parts):
            if p.size(0) == 0:
                raise ValueError(f"component {name!r} has no nodes")
            pos.append(p)
            cells.append(f.long() + offset)
            comp.append(torch.full((p.size(0),), c, dtype=torch.long))
            types.append(torch.full((p.size(0),), int(t), dtype=torch.long))
            names.append(name)
            offset += p.size(0)
        return MultiComponentMesh(torch.cat(pos), cells, torch.cat(comp), torch.cat(types), names)


def stacked_plates(
    nx: int,
    ny: int,
    num_layers: int,
    size: tuple[float, float] = (1.0, 1.0),
    gap: float = 0.5,
    cell_type: str = "triangle",
    dtype: torch.dtype = torch.float32,
) -> MultiComponentMesh:
    """``num_layers`` copies of one rectangle mesh stacked along e3, ``gap`` apart, one component each."""
    if num_layers < 1:
        raise ValueError(f"num_layers must be >= 1, got {num_layers}")
    parts = []
    for k in range(num_layers):
        pos, cells = rectangle_mesh(nx, ny, size, (0.0, 0.0, k * gap), cell_type, dtype)
        parts.append((f"ply{k}", pos, cells, NodeType.PLY))
    return MultiComponentMesh.merge(parts)


def laminate_mesh(
    scale: int = 1,
    num_plies: int = 4,
    ply_size: float = 150.0,
    ply_gap: float = 0.5,
    dtype: torch.dtype = torch.float32,
) -> MultiComponentMesh:
    """Flat stand-in for the paper's quarter stamp-forming mesh: plies between a punch and a die.

    At ``scale=1`` it matches the seed paper's discretisation: each ply is a 40 x 40 grid
    of 3,200 triangles (1,681 nodes); the punch has 66 x 65 = 4,290 quads (paper: 4,258),
    the die 75 x 68 = 5,100 quads; about 16k nodes in all. ``scale=s`` multiplies the cells
    per direction by ``s`` (so nodes by about ``s**2``). Plies lie ``ply_gap`` apart in e3,
    the die just below the lowest ply and the punch just above the highest (touching at
    distance ``ply_gap``), so every component has contact partners within a few mm.
    Topology only depends on ``scale`` and ``num_plies``; the geometry is flat.
    """
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    n = 40 * scale
    parts: list[tuple[str, Tensor, Tensor, int]] = []
    die_pos, die_cells = rectangle_mesh(
        75 * scale, 68 * scale, (1.2 * ply_size, 1.1 * ply_size), (0.0, 0.0, -ply_gap), "quad", dtype
    )
    for k in range(num_plies):
        pos, cells = rectangle_mesh(n, n, (ply_size, ply_size), (0.0, 0.0, k * ply_gap), "triangle", dtype)
        parts.append((f"ply{k}", pos, cells, NodeType.PLY))
    punch_pos, punch_cells = rectangle_mesh(
        66 * scale,
        65 * scale,
        (0.9 * ply_size, 0.9 * ply_size),
        (0.0, 0.0, num_plies * ply_gap),
        "quad",
        dtype,
    )
    parts.append(("punch", punch_pos, punch_cells, NodeType.PUNCH))
    parts.append(("die", die_pos, die_cells, NodeType.DIE))
    return MultiComponentMesh.merge(parts)
