"""Probe: a direct AMPN (settings, time) -> displacement, no rollout, against POD + GP.

    python benchmarks/direct_probe.py data/default --steps 1000 --out benchmarks/results/direct_probe.json
    python benchmarks/direct_probe.py data/default --steps 1000 --base mean \
        --out benchmarks/results/direct_probe_mean.json

A first measurement for the direct model (one forward pass per setting and time, as POD + GP
regresses whole trajectories): the initial mesh and hierarchy, the paper's node features at
t = 0 (node type, fibres, component, gripper features from the settings), the tools'
displacement at time t and a Fourier encoding of t as input; the ply nodes' displacement from
the initial state at t as output, trained with the MSE over random (trajectory, step) samples.
The contact edges are those of the initial state; with ``--base mean`` the network predicts the
departure from the mean training trajectory instead (the setting effect alone). Prints and
writes the test RMSE (mm, over ply nodes, averaged over the saved steps, as the rollouts are
scored) of the direct AMPN, POD + GP and the mean training trajectory, on the dataset's own
train/test split.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import torch
from torch import Tensor

from torch_ampn.baselines import MeanTrajectory, PODRegression
from torch_ampn.data import HierarchyCache, Trajectory, TrajectoryDataset, gripper_forces, gripper_points
from torch_ampn.forming import Normalizer
from torch_ampn.forming.features import ampn_channels, step_features
from torch_ampn.nn import RobinAMPN
from torch_ampn.rollout import rollout_rmse
from torch_ampn.transforms import ComponentRadiusGraph

TIME_FREQUENCIES = 4


def time_code(t: Tensor) -> Tensor:
    """Fourier features of the normalised time ``t`` in [0, 1], ``[2 F]``."""
    k = torch.arange(TIME_FREQUENCIES, dtype=torch.float32)
    angle = math.pi * (2.0**k) * t
    return torch.cat([angle.sin(), angle.cos()])


class DirectInputs:
    """The fixed graph of one mesh and the features of (trajectory, step) samples on it."""

    def __init__(self, traj: Trajectory, num_levels: int, radius: float, k: int) -> None:
        h = HierarchyCache(None, max_levels=num_levels)(traj)
        h["l0"].pos, h["l0"].component = traj.pos[0], traj.component  # contact of the initial state
        h = ComponentRadiusGraph(radius, k)(h)
        self.levels = h.num_levels
        self.fine_index = [h.fine_index(j) for j in range(1, self.levels)]
        self.edge_index = {key: h[key].edge_index for key in h.edge_types}
        self.num_components = traj.num_components

    def features(self, traj: Trajectory, step: int) -> tuple[dict, dict]:
        pos0 = traj.pos[0].float()
        tools = ~traj.ply_mask
        bc = torch.zeros_like(pos0)
        bc[tools] = (traj.pos[step] - traj.pos[0]).float()[tools]  # the tools' displacement at t
        points = gripper_points(pos0, traj.gripper_nodes)
        force = gripper_forces(points, traj.gripper_anchor.float(), traj.gripper_force.float())
        x_dict, e_dict = step_features(
            pos0, pos0, torch.zeros_like(pos0), bc, traj.node_type, traj.component, traj.fiber.float(),
            points, force, self.fine_index, self.edge_index, self.num_components,
        )  # fmt: skip
        code = time_code(torch.tensor(step / traj.num_steps))
        x_dict["l0"] = torch.cat([x_dict["l0"], code.expand(pos0.size(0), -1)], 1)
        return x_dict, e_dict


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--levels", type=int, default=3, help="1: the flat network")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--base", choices=["initial", "mean"], default="initial",
        help="predict the displacement from the initial state, or from the mean training trajectory",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/direct_probe.json"))
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    train = list(TrajectoryDataset(args.data_dir, "train"))
    test = list(TrajectoryDataset(args.data_dir, "test"))
    inputs = DirectInputs(train[0], args.levels, radius=12.0, k=1)
    sizes = ampn_channels(train[0].num_components, train[0].gripper_nodes.size(0))
    sizes["fine_in_channels"] += 2 * TIME_FREQUENCIES
    model = RobinAMPN(
        **sizes, hidden_channels=args.hidden, mlp_channels=args.hidden, num_levels=inputs.levels
    )
    node_norm = {
        "fine": Normalizer(sizes["fine_in_channels"]),
        "coarse": Normalizer(sizes["coarse_in_channels"]),
    }
    edge_norm: dict[str, Normalizer] = {}
    target_norm = Normalizer(3)
    ply = train[0].ply_mask
    mean_pos = torch.stack([t.pos.float() for t in train]).mean(0)  # [T+1, N, 3]

    def base(traj: Trajectory, step: int) -> Tensor:
        """What the network's output is added to: the initial state or the mean trajectory at ``step``."""
        return traj.pos[0].float() if args.base == "initial" else mean_pos[step]

    for traj in train[:8]:  # statistics from a sample of the training windows
        for step in range(1, traj.num_steps + 1, 5):
            x_dict, e_dict = inputs.features(traj, step)
            for name, x in x_dict.items():
                node_norm["fine" if name == "l0" else "coarse"].update(x)
            for (_, rel, _), e in e_dict.items():
                edge_norm.setdefault(rel, Normalizer(e.size(1))).update(e)
            target_norm.update((traj.pos[step].float() - base(traj, step))[ply])
    for n in (*node_norm.values(), *edge_norm.values(), target_norm):
        n.freeze()

    def forward(traj: Trajectory, step: int) -> Tensor:
        x_dict, e_dict = inputs.features(traj, step)
        x_dict = {name: node_norm["fine" if name == "l0" else "coarse"](x) for name, x in x_dict.items()}
        e_dict = {key: edge_norm[key[1]](e) for key, e in e_dict.items()}
        return model(x_dict, inputs.edge_index, e_dict)  # [N, 3] normalised displacement

    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, args.steps)
    g = torch.Generator().manual_seed(args.seed)
    start = time.perf_counter()
    for it in range(args.steps):
        traj = train[int(torch.randint(len(train), (1,), generator=g))]
        step = int(torch.randint(1, traj.num_steps + 1, (1,), generator=g))
        target = target_norm(traj.pos[step].float() - base(traj, step))
        loss = (forward(traj, step) - target)[ply].square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        if (it + 1) % 250 == 0:
            seconds = time.perf_counter() - start
            print(f"step {it + 1}/{args.steps}: loss {float(loss.detach()):.4f} ({seconds:.0f} s)")
    train_seconds = time.perf_counter() - start

    model.eval()
    rmse = {"direct_ampn": [], "pod_gp": [], "mean_trajectory": []}
    baselines = {"pod_gp": PODRegression("gp").fit(train), "mean_trajectory": MeanTrajectory().fit(train)}
    start = time.perf_counter()
    with torch.no_grad():
        for traj in test:
            pred = traj.pos.clone().float()
            for step in range(1, traj.num_steps + 1):
                u = target_norm.denormalize(forward(traj, step))
                pred[step, ply] = (base(traj, step) + u)[ply]
            rmse["direct_ampn"].append(float(rollout_rmse(pred, traj.pos, ply)[1:].mean()))
            for name, baseline in baselines.items():
                rmse[name].append(float(rollout_rmse(baseline.predict(traj), traj.pos, ply)[1:].mean()))
    predict_seconds = (time.perf_counter() - start) / len(test)
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "data": str(args.data_dir),
        "train": len(train),
        "test": len(test),
        "levels": inputs.levels,
        "hidden": args.hidden,
        "parameters": sum(p.numel() for p in model.parameters()),
        "steps": args.steps,
        "base": args.base,
        "train_seconds": train_seconds,
        "predict_seconds_per_test_trajectory": predict_seconds,
        "rmse_mm": {k: sum(v) / len(v) for k, v in rmse.items()},
        "rmse_mm_per_trajectory": rmse,
    }
    print(json.dumps(result["rmse_mm"], indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, args.out)


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    main()
