"""Part-quality measures against hand cases: flat, a sine of known amplitude, rigid motions, simple shear."""

import math

import pytest
import torch

from torch_ampn.data import Trajectory
from torch_ampn.data.mesh import MultiComponentMesh, rectangle_mesh
from torch_ampn.data.node_type import NodeType
from torch_ampn.design import (
    MEASURES,
    WrinkleOperator,
    draw_in_field,
    median_edge_length,
    part_quality,
    penetration_field,
    shear_field,
    wrinkle_field,
)

SIZE = 60.0


def _part(n: int = 24, cell_type: str = "triangle", fibre_deg: float = 0.0, die: bool = False) -> Trajectory:
    """One flat square ply ``SIZE`` mm wide of ``n x n`` cells at e3 = 0 (and a flat die 1 mm below)."""
    pos, cells = rectangle_mesh(n, n, (SIZE, SIZE), cell_type=cell_type, dtype=torch.float64)
    parts = [("ply", pos, cells, NodeType.PLY)]
    if die:
        tool, tool_cells = rectangle_mesh(
            8, 8, (SIZE + 20, SIZE + 20), (-10.0, -10.0, -1.0), "quad", torch.float64
        )
        parts.append(("die", tool, tool_cells, NodeType.DIE))
    mesh = MultiComponentMesh.merge(parts)
    fiber = torch.zeros_like(mesh.pos)
    angle = math.radians(fibre_deg)
    fiber[mesh.node_type == NodeType.PLY] = torch.tensor(
        [math.cos(angle), math.sin(angle), 0.0], dtype=mesh.pos.dtype
    )
    return Trajectory(
        pos=mesh.pos[None].float(),
        time=torch.zeros(1),
        cells=mesh.cells,
        component=mesh.component,
        node_type=mesh.node_type,
        fiber=fiber.float(),
        names=mesh.names,
        gripper_nodes=torch.zeros(0, 1, dtype=torch.long),
        gripper_anchor=torch.zeros(0, 3),
        gripper_force=torch.zeros(0),
    )


def _ply(traj: Trajectory) -> torch.Tensor:
    return traj.node_type == NodeType.PLY


def _moved(traj: Trajectory, fn) -> torch.Tensor:
    """Positions ``[N, 3]`` with the ply nodes mapped by ``fn(x [M, 3]) -> [M, 3]`` (float64)."""
    pos = traj.pos[0].double().clone()
    ply = _ply(traj)
    pos[ply] = fn(pos[ply])
    return pos


def test_a_flat_ply_and_a_paraboloid_have_no_wrinkles():
    traj = _part()
    assert wrinkle_field(traj, traj.pos[0]).abs().max() < 1e-9
    dome = _moved(
        traj,
        lambda x: (
            x + torch.stack([0 * x[:, 0], 0 * x[:, 0], ((x[:, 0] - 30) ** 2 + (x[:, 1] - 30) ** 2) / 120], 1)
        ),
    )
    assert wrinkle_field(traj, dome).abs().max() < 1e-6  # a quadric is fitted exactly


@pytest.mark.parametrize("cell_type", ["triangle", "quad"])
def test_a_sine_wave_gives_its_amplitude_back(cell_type):
    """z = A sin(2 pi x / L) with L = the radius: the fitted quadric cannot follow it, |w| peaks at A."""
    traj = _part(n=60, cell_type=cell_type)  # h = 1 mm
    amplitude, wavelength = 0.8, 10.0
    wavy = _moved(
        traj,
        lambda x: (
            x
            + torch.stack(
                [0 * x[:, 0], 0 * x[:, 0], amplitude * torch.sin(2 * math.pi * x[:, 0] / wavelength)], 1
            )
        ),
    )
    w = wrinkle_field(traj, wavy, radius=wavelength)
    inner = (traj.pos[0, :, :2] - SIZE / 2).abs().max(1).values < SIZE / 2 - wavelength
    assert abs(float(w[inner].abs().max()) - amplitude) < 0.1 * amplitude
    assert median_edge_length(traj) == pytest.approx(1.0)
    # the default radius (3 edges) on the coarser mesh sees a wave of 6 edges as a wrinkle too
    q = part_quality(traj, wavy, wrinkle_radius=wavelength)
    assert q["wrinkle_amplitude"] == pytest.approx(float(w.abs().max()))


def test_rigid_motions_have_no_shear_no_wrinkles_and_no_mean_draw_in():
    traj = _part(cell_type="quad", fibre_deg=30.0)
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    tilt = torch.linalg.matrix_exp(
        torch.tensor([[0.0, 0.0, 0.3], [0.0, 0.0, 0.0], [-0.3, 0.0, 0.0]], dtype=torch.float64)
    )
    moved = _moved(traj, lambda x: x @ (tilt @ rot).T + torch.tensor([5.0, -2.0, 7.0], dtype=torch.float64))
    _, shear = shear_field(traj, moved)
    assert shear.abs().max() < 1e-9
    assert wrinkle_field(traj, moved).abs().max() < 1e-9
    shifted = _moved(traj, lambda x: x + torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64))
    nodes, draw_in = draw_in_field(traj, shifted)
    assert abs(float(draw_in.mean())) < 1e-9  # +3 mm on one edge, -3 mm on the opposite one
    left = traj.pos[0, nodes, 0] == 0
    assert torch.allclose(
        draw_in[left & (traj.pos[0, nodes, 1] > 0) & (traj.pos[0, nodes, 1] < SIZE)],
        torch.tensor(3.0, dtype=torch.float64),
    )


def test_a_uniform_contraction_draws_the_edges_in_by_hand():
    traj = _part()
    s = 0.9
    centre = torch.tensor([SIZE / 2, SIZE / 2, 0.0], dtype=torch.float64)
    nodes, draw_in = draw_in_field(traj, _moved(traj, lambda x: centre + s * (x - centre)))
    xy = traj.pos[0, nodes, :2].double()
    on_x = (xy[:, 0] == 0) | (xy[:, 0] == SIZE)
    on_y = (xy[:, 1] == 0) | (xy[:, 1] == SIZE)
    half = (1 - s) * SIZE / 2
    torch.testing.assert_close(draw_in[on_x ^ on_y], torch.full_like(draw_in[on_x ^ on_y], half))
    torch.testing.assert_close(
        draw_in[on_x & on_y], torch.full_like(draw_in[on_x & on_y], half * math.sqrt(2))
    )
    assert nodes.numel() == 4 * 24  # every boundary node once


@pytest.mark.parametrize("cell_type", ["triangle", "quad"])
@pytest.mark.parametrize("fibre_deg", [0.0, 45.0])
def test_a_simple_shear_along_the_fibres_gives_its_angle(cell_type, fibre_deg):
    traj = _part(cell_type=cell_type, fibre_deg=fibre_deg)
    gamma = math.radians(12.0)
    a = torch.tensor(
        [math.cos(math.radians(fibre_deg)), math.sin(math.radians(fibre_deg)), 0.0], dtype=torch.float64
    )
    b = torch.tensor([-a[1], a[0], 0.0], dtype=torch.float64)
    sheared = _moved(traj, lambda x: x + math.tan(gamma) * (x @ b)[:, None] * a)
    comps, shear = shear_field(traj, sheared)
    torch.testing.assert_close(shear, torch.full_like(shear, 12.0))
    assert comps.unique().tolist() == [0]


def test_penetration_is_the_depth_behind_the_tool():
    traj = _part(die=True)
    pos = traj.pos[0].double().clone()
    assert penetration_field(traj, pos).abs().max() == 0.0
    node = 24 * 25 // 2  # a ply node near the middle
    pos[node, 2] = -1.3
    depth = penetration_field(traj, pos)
    assert depth[node] == pytest.approx(0.3)
    assert depth.sum() == pytest.approx(0.3)  # nothing else behind the die


def test_wrong_positions_and_a_tiny_radius_are_refused():
    traj = _part()
    with pytest.raises(ValueError, match=r"pos must be \[N, 3\]"):
        wrinkle_field(traj, traj.pos)
    with pytest.raises(ValueError, match="fewer than 6 nodes"):
        wrinkle_field(traj, traj.pos[0], radius=1.0)


def test_one_wrinkle_operator_judges_many_positions_of_its_part():
    """Built once from the reference, it equals a fresh fit for any positions; another part is refused."""
    traj = _part(n=12)
    operator = WrinkleOperator(traj, radius=15.0)
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        pos = traj.pos[0].double() + 0.3 * torch.randn(traj.num_nodes, 3, generator=g, dtype=torch.float64)
        # reference: the same quadratic fit solved directly, node by node, in float64
        ref = traj.pos[0].double()
        expected = torch.zeros(traj.num_nodes, dtype=torch.float64)
        for i in range(traj.num_nodes):
            near = ((ref - ref[i]).norm(dim=1) <= 15.0).nonzero().squeeze(1)
            du, dv = ((ref[near, 0] - ref[i, 0]) / 15.0), ((ref[near, 1] - ref[i, 1]) / 15.0)
            basis = torch.stack([torch.ones_like(du), du, dv, du * du, du * dv, dv * dv], 1)
            coef = torch.linalg.lstsq(basis, pos[near]).solution  # [6, 3]
            n = torch.linalg.cross(coef[1], coef[2])
            expected[i] = ((pos[i] - coef[0]) * n / n.norm()).sum()
        torch.testing.assert_close(operator(pos), expected, atol=1e-9, rtol=0)
    assert operator.applies_to(traj) and not operator.applies_to(_part(n=10))


def test_measure_maps_place_each_field_on_its_ply(tmp_path):
    """The fields behind the maps are the measures' own, on the right points; the figure is written."""
    from torch_ampn.design.plots import field_of, measure_field, plot_measure_maps

    traj = _part(n=12, die=True)
    moved = _moved(traj, lambda x: x * torch.tensor([0.9, 1.0, 1.0], dtype=x.dtype))  # contraction along e1
    ply = _ply(traj)
    ((points, values),) = measure_field(traj, moved, "wrinkle")
    torch.testing.assert_close(points, moved[ply])
    torch.testing.assert_close(values, wrinkle_field(traj, moved)[ply])
    ((points, values),) = measure_field(traj, moved, "draw_in")
    nodes, draw_in = draw_in_field(traj, moved)
    torch.testing.assert_close(points, moved[nodes])
    torch.testing.assert_close(values, draw_in)
    ((points, values),) = measure_field(traj, moved, "shear")
    assert points.shape == (traj.cells[0].size(0), 3) and values.abs().max() < 1e-9  # a stretch, no shear
    torch.testing.assert_close(points, moved[traj.cells[0]].mean(1))
    assert field_of("draw_in_mean") == "draw_in" and field_of("penetration_max") == "penetration"
    with pytest.raises(ValueError, match="unknown measure 'smoothness'"):
        field_of("smoothness")
    path = plot_measure_maps(tmp_path / "maps.png", traj, {"a": moved, "b": traj.pos[0]}, "draw_in_max")
    assert path.stat().st_size > 1000


def test_part_quality_of_some_measures_equals_those_of_all():
    traj = _part(n=12, die=True)
    moved = _moved(traj, lambda x: x + torch.stack([0.05 * x[:, 1], 0 * x[:, 0], torch.sin(x[:, 0] / 5)], 1))
    every = part_quality(traj, moved)
    assert list(every) == list(MEASURES)
    for names in (["wrinkle_rms"], ["shear_max", "draw_in_mean"], ["penetration_max"]):
        assert part_quality(traj, moved, names=names) == {n: every[n] for n in names}
    with pytest.raises(ValueError, match=r"unknown measures \['flatness'\]"):
        part_quality(traj, moved, names=["flatness"])
