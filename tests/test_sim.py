"""Physical sanity of the embedded stamp-forming simulator on a coarse run."""

import json
import math
import os

import pytest
import torch

from torch_ampn.data import NodeType
from torch_ampn.sim import StampFormingConfig, simulate, simulate_batch
from torch_ampn.sim.geometry import die_surface, punch_surface
from torch_ampn.sim.mechanics import OrthotropicMembrane, QuadraticBending
from torch_ampn.sim.simulate import LaminateModel, build_mesh, sample_process

CFG = StampFormingConfig(ply_cells=10, punch_cells=(8, 8), die_cells=(9, 9))

#: The module's tests share one worker (pytest-xdist): ``runs`` (two coarse runs, about half a minute)
#: is simulated once, not once per worker.
pytestmark = pytest.mark.xdist_group("sim_runs")


@pytest.fixture(scope="module")
def runs():
    return simulate_batch(CFG, seeds=[0, 1], compile=bool(int(os.environ.get("AMPN_TEST_COMPILE", "0"))))


def test_tools_follow_their_prescribed_motion(runs):
    traj = runs[0]
    assert traj.pos.shape[0] == CFG.num_steps + 1
    punch = traj.node_type == NodeType.PUNCH
    die = traj.node_type == NodeType.DIE
    u = traj.displacement()
    assert torch.allclose(u[-1, punch, 2], torch.full((int(punch.sum()),), -60.0), atol=1e-4)
    assert torch.allclose(u[:, punch, :2], torch.zeros_like(u[:, punch, :2]))
    expected = -60.0 * torch.arange(CFG.num_steps + 1) / CFG.num_steps
    assert torch.allclose(u[:, punch, 2], expected[:, None].expand(-1, int(punch.sum())), atol=1e-4)
    assert torch.equal(u[:, die], torch.zeros_like(u[:, die]))


def test_plies_are_formed_into_the_die(runs):
    traj = runs[0]
    ply = traj.ply_mask
    pos0 = traj.pos[0]
    # the bottom ply's node nearest to the dome apex ends at the die's cavity bottom
    apex = torch.tensor([CFG.dome_centre, 0.0])
    bottom = ply & (traj.component == 0)
    i = torch.where(bottom, (pos0[:, :2] - apex).norm(dim=1), torch.inf).argmin()
    depth = CFG.dome_depth + 0.5 * CFG.ply_thickness
    assert traj.pos[-1, i, 2].item() == pytest.approx(-depth, abs=0.5)
    # travel of the punch beyond first contact, minus nothing: the stack is pressed flat
    assert traj.displacement()[-1, i, 2].item() == pytest.approx(-(CFG.stroke - CFG.punch_clearance), abs=0.6)
    # material is drawn in from the free edge e1 = ply_size[0]
    edge = ply & ((pos0[:, 0] - CFG.ply_size[0]).abs() < 1e-6)
    assert traj.pos[-1, edge, 0].mean() < CFG.ply_size[0] - 5.0


def test_no_penetration_of_tools_beyond_tolerance(runs):
    """Distance along the tool normal from ply k to its tool, less the plies between: >= -1 mm."""
    tol = 1.0  # mm (two ply thicknesses: squeezed folds at the end of the stroke), stated in the README
    for traj in runs:
        ply = traj.ply_mask
        layer = traj.component[ply].double()
        h = CFG.ply_thickness
        for k in range(CFG.num_steps + 1):
            x = traj.pos[k, ply].double()
            travel = CFG.stroke * k / CFG.num_steps
            die_z, die_grad = die_surface(x[:, :2], CFG)
            punch_z, punch_grad = punch_surface(x[:, :2], travel, CFG)
            die_gap = (x[:, 2] - (die_z + layer * h)) * torch.rsqrt(1 + die_grad.pow(2).sum(1))
            punch_gap = (punch_z - (CFG.num_plies - 1 - layer) * h - x[:, 2]) * torch.rsqrt(
                1 + punch_grad.pow(2).sum(1)
            )
            assert die_gap.min() > -tol, f"die penetration {die_gap.min():.2f} mm at step {k}"
            assert punch_gap.min() > -tol, f"punch penetration {punch_gap.min():.2f} mm at step {k}"


def test_plies_keep_their_stacking_order(runs):
    traj = runs[0]
    per_ply = int((traj.component == 0).sum())
    for k in range(0, CFG.num_steps + 1, 10):
        x = traj.pos[k]
        for p in range(1, CFG.num_plies):
            upper, lower = x[p * per_ply : (p + 1) * per_ply], x[(p - 1) * per_ply : p * per_ply]
            # distance of every upper node to the nearest lower node: never (nearly) coincident
            d = torch.cdist(upper.double(), lower.double()).min(1).values
            assert (d > 0.5 * CFG.ply_thickness).float().mean() > 0.98, f"plies {p - 1}/{p} merge at step {k}"


def test_symmetry_conditions_hold(runs):
    for traj in runs:
        ply = traj.ply_mask
        pos0 = traj.pos[0]
        on_x0 = ply & (pos0[:, 0].abs() < 1e-6)
        on_y0 = ply & (pos0[:, 1].abs() < 1e-6)
        assert on_x0.sum() > 0 and on_y0.sum() > 0
        assert traj.pos[:, on_x0, 0].abs().max() < 1e-6
        assert traj.pos[:, on_y0, 1].abs().max() < 1e-6
        assert traj.pos[:, ply, :2].min() > -1e-6  # nothing crosses the symmetry planes


def test_motion_stays_bounded(runs):
    for traj in runs:
        assert torch.isfinite(traj.pos).all()
        step = (traj.pos[1:] - traj.pos[:-1]).norm(dim=-1)  # mm per saved step
        assert step.max() < 25.0
        assert step[:, traj.ply_mask].mean() < 1.5  # punch moves 1.2 mm per step


def test_same_seed_same_output_and_grippers_matter(runs):
    alone = simulate(CFG, seed=0, device="cpu")
    assert torch.equal(alone.pos, runs[0].pos)  # batching does not change a trajectory
    ply = runs[0].ply_mask
    diff = (runs[0].pos[-1, ply] - runs[1].pos[-1, ply]).norm(dim=-1)
    assert diff.pow(2).mean().sqrt() > 0.05  # other gripper settings, measurably other shapes
    assert not torch.equal(runs[0].gripper_force, runs[1].gripper_force)
    f0, f1 = runs[0].gripper_force, runs[1].gripper_force
    assert ((f0 >= 0) & (f0 <= 100) & (f1 >= 0) & (f1 <= 100)).all()


def test_a_solver_step_runs_where_the_model_is():
    """Every tensor a step uses follows ``LaminateModel.to``: a step on the meta device (shapes only)
    fails with a device mismatch if one is made on the CPU inside the step."""
    mesh = build_mesh(CFG)
    model = LaminateModel(CFG, mesh, [sample_process(CFG, 0), sample_process(CFG, 1)]).to("meta")
    for part in (model, model.membrane, model.bending):
        assert all(v.device.type == "meta" for v in vars(part).values() if isinstance(v, torch.Tensor))
    x, v = model.x0.clone(), torch.zeros_like(model.x0)
    model.refresh_pairs(x)
    travel = torch.tensor(1.0, dtype=x.dtype, device=x.device)
    x, v, work = model.step_function()(x, v, travel, model.pairs_lower, model.pair_friction_cap)
    assert x.device.type == "meta" and x.shape == (2 * model.n, 3) and v.shape == x.shape
    assert work.device.type == "meta" and work.shape == (2, 6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_the_simulator_on_cuda_follows_the_cpu_run():
    cfg = StampFormingConfig.from_dict({**CFG.to_dict(), "num_steps": 4})
    cpu, gpu = simulate(cfg, seed=0), simulate(cfg, seed=0, device="cuda")
    assert gpu.pos.device.type == "cpu" and gpu.pos.shape == cpu.pos.shape
    assert torch.equal(gpu.pos[0], cpu.pos[0])
    # float64 in another summation order: equal to far below the mesh's scale over a few steps
    assert (gpu.pos - cpu.pos).abs().max() < 1e-3


def test_trajectory_is_valid_and_round_trips(runs, tmp_path):
    from torch_ampn.data import Trajectory

    traj = runs[0]
    traj.validate()
    traj.save(tmp_path / "t.pt")
    back = Trajectory.load(tmp_path / "t.pt")
    assert torch.equal(back.pos, traj.pos)
    assert back.meta["seed"] == 0 and back.meta["config"]["ply_cells"] == 10
    fiber = traj.fiber[traj.ply_mask]
    assert torch.allclose(fiber.norm(dim=1), torch.ones(fiber.size(0)))
    angles = torch.rad2deg(torch.atan2(fiber[:, 1], fiber[:, 0])).round()
    assert set(angles.unique().tolist()) == {0.0, 45.0, 90.0, -45.0}


def _random_sheet(seed: int = 0):
    from torch_ampn.data import rectangle_mesh

    pos, tri = rectangle_mesh(5, 4, (5.0, 4.0), dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    x = pos + 0.2 * torch.randn(pos.shape, generator=g, dtype=torch.float64)
    return pos, tri, x


def test_membrane_forces_are_minus_energy_gradient():
    pos, tri, x = _random_sheet()
    angle = torch.full((tri.size(0),), math.radians(30.0), dtype=torch.float64)
    membrane = OrthotropicMembrane(pos[:, :2], tri, angle, 100.0, 10.0, 1.0, 0.2)
    xr = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(membrane.energy(xr), xr)
    assert torch.allclose(membrane.forces(x), -grad, atol=1e-10)
    # no force in the reference state or after a rigid rotation
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert membrane.forces(pos).abs().max() < 1e-12
    assert membrane.forces(pos @ rot.T + 3.0).abs().max() < 1e-10


def test_membrane_is_stiffer_along_the_fibre():
    pos, tri, _ = _random_sheet()
    angle = torch.zeros(tri.size(0), dtype=torch.float64)
    membrane = OrthotropicMembrane(pos[:, :2], tri, angle, 100.0, 10.0, 1.0, 1.0)
    stretch_e1 = pos * torch.tensor([1.01, 1.0, 1.0], dtype=torch.float64)
    stretch_e2 = pos * torch.tensor([1.0, 1.01, 1.0], dtype=torch.float64)
    assert membrane.energy(stretch_e1) / membrane.energy(stretch_e2) == pytest.approx(10.0, rel=1e-2)


def test_bending_energy_gradient_and_invariance():
    pos, tri, x = _random_sheet(1)
    interior = (pos[:, 0] > 0) & (pos[:, 0] < 5) & (pos[:, 1] > 0) & (pos[:, 1] < 4)
    bending = QuadraticBending(pos[:, :2], tri, interior, 3.0)
    xr = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(bending.energy(xr), xr)
    assert torch.allclose(bending.forces(x), -grad, atol=1e-10)
    rot = torch.linalg.matrix_exp(
        torch.tensor([[0.0, -0.3, 0.2], [0.3, 0.0, -0.1], [-0.2, 0.1, 0.0]]).double()
    )
    assert bending.energy(pos @ rot.T + 1.0) < 1e-20  # rigid motions of the flat sheet
    bent = pos.clone()
    bent[:, 2] = 0.1 * (pos[:, 0] - 2.5) ** 2  # a cylinder-like bend costs energy
    assert bending.energy(bent) > 1e-3


def test_unstable_or_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="substeps=1 is unstable"):
        simulate(
            StampFormingConfig(ply_cells=4, punch_cells=(2, 2), die_cells=(2, 2), num_steps=2, substeps=1)
        )
    with pytest.raises(ValueError, match="ply_cells"):
        simulate(StampFormingConfig(ply_cells=1))
    with pytest.raises(ValueError, match="gripper_force_range"):
        simulate(StampFormingConfig(gripper_force_range=(10.0, 0.0)))


@pytest.mark.parametrize("cfg", [StampFormingConfig(), StampFormingConfig.paper(), CFG])
def test_config_from_dict_inverts_to_dict(cfg):
    assert StampFormingConfig.from_dict(cfg.to_dict()) == cfg
    as_json = json.loads(json.dumps(cfg.to_dict()))  # tuples become lists in JSON
    assert StampFormingConfig.from_dict(as_json) == cfg


def test_config_from_dict_overrides_a_base_and_refuses_unknown_keys():
    overrides = {"ply_cells": 24, "punch_cells": [5, 6]}
    cfg = StampFormingConfig.from_dict(overrides, base=StampFormingConfig.paper())
    assert cfg == StampFormingConfig.paper(ply_cells=24, punch_cells=(5, 6))
    assert StampFormingConfig.from_dict({"num_steps": 7}) == StampFormingConfig(num_steps=7)
    with pytest.raises(ValueError, match="unknown setting\\(s\\) 'ply_cell', 'stroek'"):
        StampFormingConfig.from_dict({"stroek": 1.0, "ply_cells": 4, "ply_cell": 4})
    with pytest.raises(TypeError, match="must be a mapping"):
        StampFormingConfig.from_dict([("ply_cells", 4)])


@pytest.mark.parametrize("cfg", [CFG, StampFormingConfig(gripper_clamp_radius=15.0)])
def test_settings_added_later_are_written_only_away_from_their_default(cfg):
    from torch_ampn.sim.config import ADDED_LATER

    values = cfg.to_dict()
    assert ("gripper_clamp_radius" in values) == (
        cfg.gripper_clamp_radius != ADDED_LATER["gripper_clamp_radius"]
    )
    assert StampFormingConfig.from_dict(values) == cfg  # the default fills the missing key


def test_a_clamp_shares_the_gripper_force_over_the_nodes_within_its_radius():
    """``gripper_clamp_radius = 0``: one node per ply pulls force / P towards the anchor (the
    needle); a radius r: every node of that ply within r of it, the ply's share split equally,
    each towards the anchor shifted by its offset (built by brute force from the layout)."""
    from torch_ampn.sim.simulate import _gripper_layout

    mesh, process = build_mesh(CFG), sample_process(CFG, 0)
    needle = LaminateModel(CFG, mesh, [process])
    clamp = LaminateModel(
        StampFormingConfig.from_dict({"gripper_clamp_radius": 20.0}, base=CFG), mesh, [process]
    )
    per_ply, plies, x0 = needle.per_ply, CFG.num_plies, mesh.pos[: needle.n]
    nodes, anchors = _gripper_layout(CFG, x0, per_ply, process[0])
    force = process[1]
    assert torch.equal(needle.gripper_index, nodes.reshape(-1))
    assert torch.equal(needle.gripper_anchor, anchors.repeat_interleave(plies, 0))
    assert torch.equal(needle.gripper_pull, force.repeat_interleave(plies) / plies)
    index, anchor, pull = [], [], []
    for g in range(CFG.num_grippers):
        for centre in nodes[g].tolist():
            first = centre // per_ply * per_ply
            near = [
                i
                for i in range(first, first + per_ply)
                if i != centre and (x0[i] - x0[centre]).norm() <= 20.0
            ]
            assert near  # more than the needle's node
            for i in [centre, *near]:
                index.append(i)
                anchor.append(anchors[g] + x0[i] - x0[centre])
                pull.append(float(force[g]) / (plies * (1 + len(near))))
    assert clamp.gripper_index.tolist() == index
    torch.testing.assert_close(clamp.gripper_anchor, torch.stack(anchor), rtol=0, atol=1e-12)
    torch.testing.assert_close(
        clamp.gripper_pull, torch.tensor(pull, dtype=torch.float64), rtol=1e-15, atol=0
    )
    assert clamp.gripper_pull.sum() == pytest.approx(float(force.sum()))  # all of the force, shared


def test_a_record_written_before_settings_existed_reads_back_with_the_physics_of_its_day():
    """A complete ``to_dict`` of data version 2, as its ``dataset.json`` holds it (without the
    settings added since), gives data version 2's physics; a partial dict overrides the defaults."""
    from torch_ampn.sim.config import ADDED_LATER, PHYSICS_V2

    v2 = StampFormingConfig(**PHYSICS_V2)
    record = {k: v for k, v in v2.to_dict().items() if k not in ADDED_LATER}
    assert StampFormingConfig.from_dict(record) == v2
    assert StampFormingConfig.from_dict(record).ply_contact == "node"
    partial = StampFormingConfig.from_dict({"ply_cells": 5})
    assert partial.ply_contact == StampFormingConfig().ply_contact == "face"
    assert partial.matrix_viscosity == StampFormingConfig().matrix_viscosity > 0
