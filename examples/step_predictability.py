"""How predictable is the next step of a dataset? One-step references from the data alone.

    python examples/step_predictability.py data/default/test [--every 5]
    python examples/step_predictability.py data/default/test \
        --ckpt outputs/quickstart_nextstep/checkpoints/best.ckpt
        (a next-step model's checkpoint: `torch-ampn fit --config examples/configs/quickstart.yaml`)

For every step t of the trajectories in a folder, over ply nodes, averaged over trajectories:

* ``zero``: one-step RMSE of predicting no motion, i.e. the size of the residual du^t (mm);
* ``const_vel``: one-step RMSE of repeating the last residual, du^t = du^{t-1} (mm);
* ``cos``: mean cosine between du^t and du^{t-1} (1 = steady motion, ~0 = direction changes
  from step to step);
* ``max``: the largest single-node residual |du^t| (mm);
* ``model`` (with ``--ckpt``): the one-step RMSE of a trained model fed the true state at
  t-1 (teacher forcing), to set against ``zero`` and ``const_vel``.

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


def model_step_errors(module, traj: Trajectory, hierarchy, seed: int = 0) -> torch.Tensor:
    """Teacher-forced one-step RMSE over ply nodes of ``module`` (a ``NextStepLightningModule``), ``[T]``.

    At every step t the model gets the true window (t-1, t) (:func:`~torch_ampn.data.dataset.step_sample`
    with contact edges from the true positions) and its predicted residual is compared with x^t - x^{t-1}.
    """
    from torch_ampn.data.dataset import step_sample

    surrogate = module.surrogate
    errors = []
    for t in range(1, traj.num_steps + 1):
        data = step_sample(traj, t, hierarchy)
        if surrogate.contact is not None:
            data = surrogate.contact(data)
        with torch.no_grad():
            residual = surrogate.predict_residual(data, torch.Generator().manual_seed(seed + t))
        err = (residual.double() - data["l0"].target.double())[traj.ply_mask]  # [N_ply, 3]
        errors.append(err.pow(2).sum(-1).mean().sqrt())
    return torch.stack(errors)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", type=Path, help="folder of trajectory .pt files (one split)")
    parser.add_argument("--every", type=int, default=1, help="print every k-th step")
    parser.add_argument(
        "--ckpt", type=Path, default=None, help="add the teacher-forced error of this checkpoint"
    )
    parser.add_argument(
        "--min-coarse-nodes", type=int, default=16, help="hierarchy setting the model was trained with"
    )
    args = parser.parse_args()
    files = sorted(args.folder.glob("*.pt"))
    if not files:
        raise SystemExit(f"{args.folder}: no trajectory .pt files")
    trajs = [Trajectory.load(f) for f in files]
    stats = [step_statistics(traj) for traj in trajs]
    if args.ckpt is not None:
        from tqdm.auto import tqdm

        from torch_ampn.data.dataset import HierarchyCache
        from torch_ampn.training import NextStepLightningModule

        if not args.ckpt.is_file():
            raise SystemExit(f"{args.ckpt}: no such checkpoint")
        try:
            module = NextStepLightningModule.load_from_checkpoint(args.ckpt, map_location="cpu").eval()
        except ValueError as err:  # a direct model's: it predicts no next step
            raise SystemExit(f"{err} (e.g. from examples/configs/quickstart.yaml)") from None
        hierarchies = HierarchyCache(
            args.folder.parent / "cache",
            max_levels=module.surrogate.num_levels,
            min_coarse_nodes=args.min_coarse_nodes,
        )
        for traj, s in zip(tqdm(trajs, desc="teacher-forced steps", unit="trajectory"), stats, strict=True):
            s["model"] = model_step_errors(module, traj, hierarchies(traj))
    mean = {k: torch.stack([s[k] for s in stats]).mean(0) for k in stats[0]}
    mean["max"] = torch.stack([s["max"] for s in stats]).max(0).values
    print(f"{len(files)} trajectories from {args.folder}; ply nodes; mm per step")
    model_head = f" {'model':>6}" if "model" in mean else ""
    print(f"{'step':>4} {'zero':>7} {'const_vel':>9} {'cos':>6} {'max':>6}{model_head}")
    for t in range(0, mean["zero"].numel(), args.every):
        model_col = f" {mean['model'][t]:6.3f}" if "model" in mean else ""
        print(
            f"{t + 1:>4} {mean['zero'][t]:7.3f} {mean['const_vel'][t]:9.3f} "
            f"{mean['cos'][t]:6.2f} {mean['max'][t]:6.1f}{model_col}"
        )


if __name__ == "__main__":
    main()
