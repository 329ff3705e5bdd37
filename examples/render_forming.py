"""Simulate one stamp-forming process with the embedded simulator and render the formed laminate.

    python examples/render_forming.py --out outputs [--seed 0] [--paper]

Writes ``forming_seed<S>.png`` (the bottom ply at 70 % and 100 % of the process, seen
from below, mirrored to the full double-dome part, coloured by e3 displacement) and
``forming_seed<S>.pt`` (the trajectory).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from torch_ampn.sim import StampFormingConfig, simulate  # noqa: E402
from torch_ampn.viz import plot_laminate  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("outputs"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--paper", action="store_true", help="the paper's resolution (3,200 triangles per ply)"
    )
    parser.add_argument("--compile", action="store_true", help="torch.compile the solver step")
    args = parser.parse_args()

    cfg = StampFormingConfig.paper() if args.paper else StampFormingConfig()
    t0 = time.perf_counter()
    traj = simulate(cfg, seed=args.seed, progress=True, compile=args.compile)
    print(f"simulated {traj.num_nodes} nodes x {traj.num_steps} steps in {time.perf_counter() - t0:.1f} s")
    where = traj.meta["gripper_edge_fraction"]
    print(f"gripper forces {traj.gripper_force.tolist()} N at edge fractions {where}")

    u3 = traj.displacement()[..., 2]
    vmin = float(u3[:, traj.ply_mask].min())
    fig = plt.figure(figsize=(13, 5.5))
    last = None
    for j, frac in enumerate((0.7, 1.0)):
        step = round(frac * traj.num_steps)
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        last = plot_laminate(
            ax, traj.pos[step], traj.cells, traj.node_type, u3[step], vmin, 0.0, show_tools=False
        )
        ax.view_init(elev=28, azim=-62)
        ax.set_title(f"{int(frac * 100)} % of the process (step {step}), bottom ply from below")
    fig.colorbar(last, ax=fig.axes, shrink=0.6, label="e3 displacement [mm]")
    fig.suptitle(f"Embedded stamp-forming simulator: [0/45/90/-45] laminate, seed {args.seed}")
    args.out.mkdir(parents=True, exist_ok=True)
    png = args.out / f"forming_seed{args.seed}.png"
    fig.savefig(png, dpi=110)
    traj.save(args.out / f"forming_seed{args.seed}.pt")
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
