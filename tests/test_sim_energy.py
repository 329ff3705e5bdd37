"""The simulator's energy balance on hand cases, and its matrix and bending viscosity."""

import math

import pytest
import torch

from torch_ampn.sim import StampFormingConfig
from torch_ampn.sim.energy import TERMS, energy_record, energy_summary, energy_table, plot_energy
from torch_ampn.sim.mechanics import OrthotropicMembrane, QuadraticBending
from torch_ampn.sim.simulate import LaminateModel, build_mesh

# two plies, no grippers, the punch far above: nothing but the plies' own mechanics and the walls
FREE = dict(
    ply_cells=6,
    punch_cells=(4, 4),
    die_cells=(4, 4),
    ply_angles=(0.0, 90.0),
    num_grippers=0,
    punch_clearance=200.0,
)


def _model(**overrides) -> LaminateModel:
    cfg = StampFormingConfig(**{**FREE, **overrides})
    return LaminateModel(cfg, build_mesh(cfg), [(torch.empty(0), torch.empty(0))])


def _run(model: LaminateModel, x: torch.Tensor, v: torch.Tensor, substeps: int):
    """``substeps`` solver steps with the punch at rest; the state energies and the summed work."""
    step = model.step_function()
    model.refresh_pairs(x)
    travel = torch.zeros((), dtype=torch.float64)
    work = torch.zeros(1, 6, dtype=torch.float64)
    for _ in range(substeps):
        x, v, dw = step(x, v, travel, model.pairs_lower, model.pair_friction_cap)
        work += dw
    state = model.state_energies(x, v, travel, model.pairs_lower)
    return x, v, torch.cat([state, work], 1)[0]


def test_a_free_rigid_translation_has_kinetic_energy_only():
    model = _model(damping=0.0, friction_tool=0.0, friction_ply=0.0)
    lift = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)  # off the die, below the punch
    x = model.x0 + lift
    v = torch.zeros_like(x)
    v[:, 2] = 30.0  # mm/s upwards: rigid, allowed by both symmetry planes
    x, v, terms = _run(model, x, v, 40)
    # hand-computed: both plies 150 x 150 mm at areal mass 6e-6 t/mm^2 -> 0.5 m v^2 in N mm
    expected = 0.5 * (2 * 150.0 * 150.0 * 6e-6) * 30.0**2
    energy = dict(zip(TERMS, terms.tolist(), strict=True))
    assert energy["kinetic"] == pytest.approx(expected, rel=1e-12)
    for name in TERMS:
        if name != "kinetic":
            assert abs(energy[name]) < 1e-9 * expected, name
    assert torch.allclose(v[:, 2], torch.full_like(v[:, 2], 30.0))


@pytest.mark.parametrize(
    "overrides",
    [
        {"damping": 5.0},
        {"damping": 0.0, "matrix_viscosity": 0.05, "bending_viscosity": 0.5},
    ],
    ids=["mass-damping", "viscosity"],
)
def test_a_damped_free_vibration_keeps_the_sum_of_its_energies(overrides):
    """A stretched and bulged stack vibrates freely off the tools, its plies passing through each
    other (no contact): kinetic + strain energy + dissipation stays the initial strain energy
    (the work is zero), while a third of it or more is dissipated."""
    model = _model(contact_stiffness=0.0, time_step_safety=0.3, **overrides)
    x = model.x0.clone()
    x[:, 0] *= 1.02  # in-plane stretch away from the plane e1 = 0, which it keeps
    x[:, 2] += 5.0 + 2.0 * torch.sin(math.pi * x[:, 0] / 153.0) * torch.sin(math.pi * x[:, 1] / 150.0)
    v = torch.zeros_like(x)
    travel = torch.zeros((), dtype=torch.float64)
    model.refresh_pairs(x)
    start = model.state_energies(x, v, travel, model.pairs_lower)[0]
    initial = float(start[1] + start[2] + start[3])  # membrane + bending + contact
    assert initial > 1.0
    x, v, terms = _run(model, x, v, 3000)
    table = energy_table(
        energy_record(torch.stack([torch.cat([start, torch.zeros(6, dtype=start.dtype)]), terms]))
    )
    total = float(
        table["kinetic"][-1] + table["internal"][-1] + table["contact"][-1] + table["dissipated"][-1]
    )
    assert float(table["external"][-1]) == 0.0
    assert total == pytest.approx(initial, rel=0.01)
    dissipated = float(table["damping"][-1] + table["viscosity"][-1])
    assert dissipated > 0.3 * initial
    assert float(table["friction"][-1]) == 0.0


def test_viscous_forces_are_minus_the_rate_of_their_dissipation_potential_and_spare_rigid_motion():
    torch.manual_seed(0)
    ref = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.2, 0.9]], dtype=torch.float64)
    tris = torch.tensor([[0, 1, 2], [1, 3, 2]])
    eta = 0.7
    membrane = OrthotropicMembrane(
        ref, tris, torch.tensor([0.3, -0.4], dtype=torch.float64), 100.0, 3.0, 1.0, 0.2, eta
    )
    x = torch.cat([ref, torch.zeros(4, 1, dtype=torch.float64)], 1) + 0.05 * torch.randn(
        4, 3, dtype=torch.float64
    )
    v = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    _, _, r_bb, r_ab = membrane.strain_rates(x, v)
    potential = (membrane.area * eta * (0.5 * r_bb**2 + r_ab**2)).sum()
    (grad,) = torch.autograd.grad(potential, v)
    f = membrane.viscous_forces(x, v.detach())
    assert torch.allclose(f, -grad, atol=1e-12)
    assert float((f * v.detach()).sum()) == pytest.approx(-2 * float(potential.detach()), rel=1e-10)
    # a rigid velocity field (translation + rotation about an axis) has no strain rate
    omega = torch.tensor([0.3, -1.1, 0.8], dtype=torch.float64)
    rigid = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64) + torch.linalg.cross(omega.expand(4, 3), x)
    assert membrane.viscous_forces(x, rigid).abs().max() < 1e-12

    interior = torch.tensor([False, True, True, False])
    bending = QuadraticBending(ref, tris, interior, stiffness=50.0, viscosity=5.0)
    assert torch.allclose(bending.viscous_forces(v.detach()), 0.1 * bending.forces(v.detach()))
    assert float((bending.viscous_forces(v.detach()) * v.detach()).sum()) <= 0.0


def test_the_stability_limit_accounts_for_explicit_viscosity():
    plain, viscous = _model(), _model(matrix_viscosity=1.0)
    m = plain.mass[:, 0]
    omega = (plain.stiffness_bound() / m).sqrt()
    assert plain.critical_time_step() == pytest.approx(float((2.0 / omega).min()), rel=1e-12)
    zeta = viscous.viscosity_bound() / (2.0 * m * omega)
    expected = float((2.0 / omega * ((1 + zeta**2).sqrt() - zeta)).min())
    assert viscous.critical_time_step() == pytest.approx(expected, rel=1e-12)
    assert viscous.critical_time_step() < plain.critical_time_step()
    # the mass-proportional damping is implicit: it does not shorten the step
    assert _model(damping=50.0).critical_time_step() == plain.critical_time_step()


def test_a_forming_run_keeps_its_energy_balance_in_meta(tmp_path):
    from torch_ampn.sim import simulate_batch

    cfg = StampFormingConfig(ply_cells=6, punch_cells=(4, 4), die_cells=(4, 4), num_steps=10)
    traj = simulate_batch(cfg, [0])[0]
    record = traj.meta["energy"]
    assert set(record) == set(TERMS) and all(len(v) == cfg.num_steps + 1 for v in record.values())
    table = energy_table(record)
    for name in ("damping", "friction", "viscosity", "walls"):  # dissipations only grow
        assert (table[name].diff() >= -1e-9).all(), name
    assert float(table["work_punch"][-1]) > 0  # the punch pushes the plies into the die
    summary = energy_summary(record)
    assert summary["final"]["kinetic"] == pytest.approx(record["kinetic"][-1])
    path = plot_energy([("seed 0", record)], tmp_path / "energy.png", times=traj.time.tolist())
    assert path.read_bytes()[:4] == b"\x89PNG"


def test_a_record_missing_a_term_is_refused_with_its_source():
    record = {name: [0.0, 1.0] for name in TERMS if name != "friction"}
    with pytest.raises(ValueError, match="run_7.pt: field 'energy' lacks friction"):
        energy_table(record, "run_7.pt")
