"""How predictable is the next step of a dataset? One-step references from the data alone.

    python examples/step_predictability.py data/default/test [--every 5]

For every step t of the trajectories in a folder, over ply nodes, averaged over trajectories:

* ``zero``: one-step RMSE of predicting no motion, i.e. the size of the residual du^t (mm);
* ``const_vel``: one-step RMSE of repeating the last residual, du^t = du^{t-1} (mm);
* ``cos``: mean cosine between du^t and du^{t-1} (1 = steady motion, ~0 = direction changes
  from step to step);
* ``max``: the largest single-node residual |du^t| (mm).

A learned one-step model should beat ``const_vel``; where ``cos`` is small and ``max`` is many
times ``zero`` the motion changes faster than the output step resolves.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torch_ampn.data.trajectory import Trajectory


def step_statistics(traj: Trajectory) -> dict[str, torch.Tensor]:
    """Per-step statistics of one trajectory's ply residuals, each ``[T]``.

    ``const_vel`` and ``cos`` need a previous residual, so their first entry is NaN.
    """
    u = traj.displacement()  # [T + 1, N, 3]
    du = (u[1:] - u[:-1])[:, traj.ply_mask].double()  # [T, N_ply, 3]
    size = du.norm(dim=-1)  # [T, N_ply]
    change = (du[1:] - du[:-1]).norm(dim=-1)  # [T - 1, N_ply]
    cos = (du[1:] * du[:-1]).sum(-1) / (size[1:] * size[:-1]).clamp_min(1e-12)  # [T - 1, N_ply]
    nan = torch.full((1,), float("nan"), dtype=du.dtype)
    return {
        "zero": size.pow(2).mean(1).sqrt(),
        "const_vel": torch.cat([nan, change.pow(2).mean(1).sqrt()]),
        "cos": torch.cat([nan, cos.mean(1)]),
        "max": size.max(1).values,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", type=Path, help="folder of trajectory .pt files (one split)")
    parser.add_argument("--every", type=int, default=1, help="print every k-th step")
    args = parser.parse_args()
    files = sorted(args.folder.glob("*.pt"))
    if not files:
        raise SystemExit(f"{args.folder}: no trajectory .pt files")
    stats = [step_statistics(Trajectory.load(f)) for f in files]
    mean = {k: torch.stack([s[k] for s in stats]).mean(0) for k in stats[0]}
    mean["max"] = torch.stack([s["max"] for s in stats]).max(0).values
    print(f"{len(files)} trajectories from {args.folder}; ply nodes; mm per step")
    print(f"{'step':>4} {'zero':>7} {'const_vel':>9} {'cos':>6} {'max':>6}")
    for t in range(0, mean["zero"].numel(), args.every):
        print(
            f"{t + 1:>4} {mean['zero'][t]:7.3f} {mean['const_vel'][t]:9.3f} "
            f"{mean['cos'][t]:6.2f} {mean['max'][t]:6.1f}"
        )


if __name__ == "__main__":
    main()
