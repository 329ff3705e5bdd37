"""benchmarks/learning_curve.py: the fitted curve and the POD basis floor against exact cases."""

import dataclasses
import importlib.util
import math
from pathlib import Path

import torch

from torch_ampn.baselines import PODRegression
from torch_ampn.data.node_type import NodeType
from torch_ampn.testing import small_trajectory

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("learning_curve", ROOT / "benchmarks" / "learning_curve.py")
learning_curve = importlib.util.module_from_spec(spec)
spec.loader.exec_module(learning_curve)


def test_fit_curve_recovers_a_known_power_law():
    e, b, c = 0.29, 40.0, 1.2
    sizes = [24, 48, 96, 187, 24, 48]
    rmse = [math.sqrt(e**2 + b * n ** (-c)) for n in sizes]
    curve = learning_curve.fit_curve(sizes, rmse)
    assert abs(curve["e_mm"] - e) < 1e-4 and abs(curve["c"] - c) < 1e-3
    assert abs(curve["at_684"] - math.sqrt(e**2 + b * 684 ** (-c))) < 1e-4


def test_basis_floor_is_zero_on_the_basis_and_the_off_basis_part_otherwise():
    template = small_trajectory(steps=3)
    ply = template.node_type == NodeType.PLY
    x = template.pos[0, ply]  # [P, 3]

    def moved(position, shape):
        pos = template.pos.clone()
        for t in range(pos.size(0)):
            pos[t, ply] = x + t * shape
        meta = {"gripper_edge_fraction": [position], "name": f"at {position}"}
        return dataclasses.replace(template, pos=pos, gripper_force=torch.tensor([10.0]), meta=meta)

    up = torch.zeros_like(x)
    up[:, 2] = 1.0
    train = [moved(0.2, up), moved(0.8, 3 * up)]  # one mode: a uniform lift along e3
    model = PODRegression("linear", num_components=None).fit(train)
    assert learning_curve.basis_floor(model, [moved(0.5, 2 * up)]) < 1e-5  # on the line of the two
    sideways = torch.zeros_like(x)
    sideways[:, 0] = 1.0  # orthogonal to the basis and to the mean's offsets: all of it is left
    off = moved(0.5, 2 * up + sideways)
    # rollout_rmse is the RMS over the ply nodes' coordinates: t / sqrt(3) mm at steps 1..3
    expected = torch.arange(1, 4, dtype=torch.float64).mean() / 3**0.5
    assert abs(learning_curve.basis_floor(model, [off]) - float(expected)) < 1e-4
