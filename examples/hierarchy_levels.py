"""Build the AMG hierarchy of the paper-sized laminate and draw its levels.

    python examples/hierarchy_levels.py --out outputs

Writes ``hierarchy_levels.png`` (the nodes and mesh edges of one ply on every level, and
the down edges of one coarse node) and prints the per-level summary.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from torch_ampn.data import build_hierarchy, laminate_mesh  # noqa: E402


def draw_level(
    ax, pos: torch.Tensor, edge_index: torch.Tensor, keep: torch.Tensor, title: str, extent: torch.Tensor
) -> None:
    """Draw nodes ``keep`` (bool [N]) of a level and the mesh edges among them, in the e1-e2 plane.

    ``extent`` is ``[[x_min, y_min], [x_max, y_max]]`` of the drawn area.
    """
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
    ax.set_xticks([])
    ax.set_yticks([])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("outputs"))
    parser.add_argument("--scale", type=int, default=1, help="mesh refinement (1: paper resolution)")
    parser.add_argument("--cache-dir", type=Path, default=Path("outputs/cache"))
    args = parser.parse_args()

    mesh = laminate_mesh(scale=args.scale)
    h = build_hierarchy(mesh.edge_index(), mesh.num_nodes, cache_dir=args.cache_dir)
    print(h.summary())

    ply = 0  # draw the lowest ply; the other components are coarsened the same way
    fig, axes = plt.subplots(1, h.num_levels, figsize=(3.2 * h.num_levels, 3.4))
    ply_pos = mesh.pos[mesh.component == ply, :2]
    extent = torch.stack([ply_pos.min(0).values, ply_pos.max(0).values])
    for k, ax in enumerate(axes):
        fine = h.fine_index(k)
        pos, comp = mesh.pos[fine], mesh.component[fine]
        keep = comp == ply
        draw_level(
            ax,
            pos,
            h.mesh(k).edge_index,
            keep,
            f"level {k}: {int(keep.sum())} nodes in {mesh.names[ply]}",
            extent,
        )
    # Down edges of one coarse node in the middle of the ply: the fine nodes it collects from.
    centre = torch.tensor([75.0, 75.0])
    coarse_pos = mesh.pos[h.fine_index(1)]
    in_ply = mesh.component[h.fine_index(1)] == ply
    c = int(torch.where(in_ply, (coarse_pos[:, :2] - centre).norm(dim=1), torch.inf).argmin())
    src, dst = h.down(0).edge_index
    fine_nodes = src[dst == c]
    axes[0].scatter(
        *mesh.pos[fine_nodes, :2].T, s=10, c="tab:red", zorder=4, label="down edges of one l1 node"
    )
    axes[0].legend(loc="lower left", fontsize=7)
    fig.suptitle("AMG hierarchy (pyamg root-node smoothed aggregation) of the paper-sized laminate")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "hierarchy_levels.png"
    fig.savefig(path, dpi=130)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
