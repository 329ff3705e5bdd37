"""Plots of laminates and trajectories (matplotlib, headless-safe)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType


def plot_laminate(
    ax: Any,
    pos: Tensor,
    cells: list[Tensor],
    node_type: Tensor,
    color: Tensor,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str = "jet",
    show_tools: bool = True,
    mirror: bool = True,
    components: list[int] | None = None,
) -> Any:
    """Draw the plies (coloured by ``color`` per node) and, faintly, the tools on a 3-D axis.

    Args:
        ax: A matplotlib 3-D axis (``projection="3d"``).
        pos: Node positions ``[N, 3]``.
        cells: One cell tensor per component (triangles for plies, quads for tools).
        node_type: ``[N]``; components whose nodes are plies are drawn coloured.
        color: Per-node scalar ``[N]`` (e.g. e3 displacement).
        vmin: Lower end of the colour range (default: minimum of ``color`` on ply nodes).
        vmax: Upper end of the colour range (default: maximum of ``color`` on ply nodes).
        cmap: Matplotlib colour map.
        show_tools: Also draw the tools as transparent grey surfaces.
        mirror: Mirror the quarter model about both symmetry planes (shows the full part).
        components: Ply components to draw (default: all plies).

    Returns:
        The last ``Poly3DCollection`` of the plies (for a colour bar).
    """
    import matplotlib as mpl
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ply = node_type == NodeType.PLY
    vmin = float(color[ply].min()) if vmin is None else vmin
    vmax = float(color[ply].max()) if vmax is None else vmax
    norm = mpl.colors.Normalize(vmin=vmin, vmax=vmax)
    colormap = mpl.colormaps[cmap]
    signs = [(1, 1), (-1, 1), (1, -1), (-1, -1)] if mirror else [(1, 1)]
    ply_verts, ply_vals, tool_verts = [], [], []
    for c, cells_c in enumerate(cells):
        is_ply = bool(ply[cells_c[0, 0]])
        if (is_ply and components is not None and c not in components) or (not is_ply and not show_tools):
            continue
        for sx, sy in signs:
            p = pos * torch.tensor([sx, sy, 1.0], dtype=pos.dtype)
            if is_ply:
                ply_verts.extend(p[cells_c].numpy())
                ply_vals.append(color[cells_c].mean(1))
            else:
                tool_verts.extend(p[cells_c].numpy())
    # one collection per kind, so that matplotlib depth-sorts all faces of the plies together
    last = None
    if tool_verts:
        ax.add_collection3d(Poly3DCollection(tool_verts, facecolors=(0.6, 0.6, 0.6, 0.08), edgecolors="none"))
    if ply_verts:
        values = torch.cat(ply_vals).numpy()
        last = Poly3DCollection(ply_verts, cmap=colormap, norm=norm, edgecolors="none")
        last.set_array(values)  # colours follow the values (and a colour bar can use them)
        ax.add_collection3d(last)
    ext = pos.abs().max(0).values
    lim = float(ext[:2].max())
    ax.set_xlim(-lim if mirror else 0, lim)
    ax.set_ylim(-lim if mirror else 0, lim)
    ax.set_zlim(float(pos[:, 2].min()), float(pos[:, 2].max()))
    ax.set_box_aspect((1, 1, 0.45))
    ax.set_xlabel("e1 [mm]")
    ax.set_ylabel("e2 [mm]")
    ax.set_zlabel("e3 [mm]")
    return last


def _draw_level(ax: Any, pos: Tensor, edge_index: Tensor, keep: Tensor, title: str, extent: Tensor) -> None:
    """Draw nodes ``keep`` (bool [N]) of a level and the mesh edges among them, in the e1-e2 plane."""
    from matplotlib.collections import LineCollection

    src, dst = edge_index
    sel = keep[src] & keep[dst] & (src < dst)
    segments = torch.stack([pos[src[sel], :2], pos[dst[sel], :2]], 1).numpy()
    ax.add_collection(LineCollection(segments, linewidths=0.3, colors="0.55"))
    ax.scatter(pos[keep, 0], pos[keep, 1], s=2 if keep.sum() > 500 else 8, c="tab:blue", zorder=3)
    ax.set_title(title, fontsize=9)
    margin = 0.03 * (extent[1] - extent[0])
    ax.set_xlim(float(extent[0, 0] - margin[0]), float(extent[1, 0] + margin[0]))
    ax.set_ylim(float(extent[0, 1] - margin[1]), float(extent[1, 1] + margin[1]))
    ax.set_aspect("equal")


def plot_hierarchy_levels(
    hierarchy: Any, pos: Tensor, component: Tensor, names: list[str] | None = None, component_id: int = 0
) -> Any:
    """Figure of one component on every level of a hierarchy, plus the down edges of one coarse node.

    Args:
        hierarchy: A :class:`~torch_ampn.data.HierarchicalData` of the mesh.
        pos: Fine node positions ``[N, 3]`` (drawn in the e1-e2 plane).
        component: Component id of every fine node ``[N]``.
        names: Component names (for titles).
        component_id: The component to draw.

    Returns:
        The matplotlib figure (one panel per level).
    """
    import matplotlib.pyplot as plt

    h = hierarchy
    name = names[component_id] if names else f"component {component_id}"
    fig, axes = plt.subplots(1, h.num_levels, figsize=(3.2 * h.num_levels, 3.4), squeeze=False)
    axes = axes[0]
    own = pos[component == component_id, :2]
    extent = torch.stack([own.min(0).values, own.max(0).values])
    for k, ax in enumerate(axes):
        fine = h.fine_index(k)
        keep = component[fine] == component_id
        _draw_level(
            ax, pos[fine], h.mesh(k).edge_index, keep, f"level {k}: {int(keep.sum())} nodes in {name}", extent
        )
    if h.num_levels > 1:
        # the fine nodes that the coarse node nearest the component's centre collects from
        centre = extent.mean(0)
        coarse = h.fine_index(1)
        inside = component[coarse] == component_id
        c = int(torch.where(inside, (pos[coarse, :2] - centre).norm(dim=1), torch.inf).argmin())
        src, dst = h.down(0).edge_index
        sources = src[dst == c]
        axes[0].scatter(*pos[sources, :2].T, s=10, c="tab:red", zorder=4, label="down edges of one l1 node")
        axes[0].legend(loc="lower left", fontsize=7)
    return fig
