"""A family of parts: sampled parts, their configurations and a family dataset."""

import dataclasses
import json
import math

import pytest
import torch
from torch_geometric.data import Batch

from torch_ampn.cli import data as data_cli
from torch_ampn.data import HierarchyCache, NodeType, Trajectory, step_sample
from torch_ampn.forming import AMPNSurrogate, component_features
from torch_ampn.sim import (
    PartFamily,
    StampFormingConfig,
    generate_dataset,
    part_config,
    sample_part,
    simulate,
    simulate_batch,
)
from torch_ampn.sim.geometry import die_surface
from torch_ampn.sim.simulate import sample_process
from torch_ampn.testing import QUICK_SIMULATOR

TINY = StampFormingConfig(ply_cells=4, punch_cells=(3, 3), die_cells=(3, 3), num_steps=4)


def test_sampled_parts_respect_the_ranges_and_are_reproducible():
    family = PartFamily(num_plies=(2, 6), ply_angles=(0.0, 90.0, 30.0))
    parts = [sample_part(family, seed) for seed in range(200)]
    assert parts[7] == sample_part(family, 7)  # the same seed, the same part
    for part in parts:
        assert family.dome_depth[0] <= part["dome_depth"] <= family.dome_depth[1]
        assert family.dome_axis_x[0] <= part["dome_axes"][0] <= family.dome_axis_x[1]
        assert family.dome_axis_y[0] <= part["dome_axes"][1] <= family.dome_axis_y[1]
        assert family.dome_flat_top[0] <= part["dome_flat_top"] <= family.dome_flat_top[1]
        if part["shape"] == "double_dome":
            assert family.dome_centre[0] <= part["dome_centre"] <= family.dome_centre[1]
        else:
            assert part["shape"] == "single_dome" and part["dome_centre"] == 0.0
        assert 2 <= len(part["ply_angles"]) <= 6 and set(part["ply_angles"]) <= {0.0, 90.0, 30.0}
    # every option is drawn over 200 parts
    assert {len(p["ply_angles"]) for p in parts} == {2, 3, 4, 5, 6}
    assert {p["shape"] for p in parts} == {"single_dome", "double_dome"}
    assert {a for p in parts for a in p["ply_angles"]} == {0.0, 90.0, 30.0}


def test_a_part_configuration_closes_the_tools_and_shapes_the_die():
    part = {
        "shape": "single_dome", "dome_depth": 42.0, "dome_axes": [61.0, 52.0], "dome_centre": 0.0,
        "dome_flat_top": 0.3, "ply_angles": [0.0, 90.0, 0.0],
    }  # fmt: skip
    cfg = part_config(TINY, part)
    assert cfg.num_plies == 3 and cfg.ply_angles == (0.0, 90.0, 0.0) and cfg.dome_axes == (61.0, 52.0)
    assert cfg.stroke == TINY.punch_clearance + 42.0  # the punch reaches the die at the end
    assert cfg.ply_cells == TINY.ply_cells  # the resolution is the base's
    # a single dome: deepest at the origin (flat top), half a ply thickness below the bottom ply
    xy = torch.tensor([[0.0, 0.0], [10.0, 0.0], [140.0, 140.0]], dtype=torch.float64)
    z, _ = die_surface(xy, cfg)
    assert z[0].item() == pytest.approx(-0.5 * cfg.ply_thickness - 42.0)
    assert z[1].item() == pytest.approx(z[0].item())  # 10 mm is inside the flat top (0.3 x 61)
    assert z[2].item() == pytest.approx(-0.5 * cfg.ply_thickness)  # outside the cavity: flat


def _box(exponent: float) -> StampFormingConfig:
    part = {
        "shape": "box", "dome_depth": 40.0, "dome_axes": [60.0, 50.0], "dome_centre": 0.0,
        "dome_flat_top": 0.3, "ply_angles": [0.0, 90.0], "dome_exponent": exponent,
    }  # fmt: skip
    return part_config(TINY, part)


def test_a_box_punch_is_a_superellipse_with_the_gradient_of_its_depth():
    """The footprint |x/a|^p + |y/b|^p = 1 by hand; the gradient against central differences (float64)."""
    from torch_ampn.sim.geometry import dome_depth, punch_surface

    box, ellipse = _box(6.0), _box(2.0)
    assert box.dome_exponent == 6.0 and ellipse.dome_exponent == 2.0
    # along an axis every exponent gives the same profile: the flat top ends at 0.3 a, the wall at a
    on_axis = torch.tensor([[0.0, 0.0], [17.0, 0.0], [45.0, 0.0], [0.0, 30.0], [61.0, 0.0]]).double()
    torch.testing.assert_close(dome_depth(on_axis, box)[0], dome_depth(on_axis, ellipse)[0])
    # towards the corner: (0.8 a, 0.8 b) is outside the ellipse (rho = 1.13) but on the box's wall,
    # rho = (2 * 0.8^6)^(1/6) = 0.898: the bump b = (1 + cos(pi s)) / 2 with s = (rho - 0.3) / 0.7,
    # and a centred part is the union of its dome with itself, D (1 - (1 - b)^2)
    corner = torch.tensor([[0.8 * 60.0, 0.8 * 50.0]], dtype=torch.float64)
    rho = (2 * 0.8**6) ** (1 / 6)
    b = 0.5 * (1 + math.cos(math.pi * (rho - 0.3) / 0.7))
    expected = 40.0 * (1 - (1 - b) ** 2)
    assert dome_depth(corner, box)[0].item() == pytest.approx(expected, rel=1e-12)
    assert dome_depth(corner, ellipse)[0].item() == 0.0
    # the gradient on the wall, off the axes and on them, against central differences
    g = torch.Generator().manual_seed(0)
    wall = torch.rand(64, 2, generator=g, dtype=torch.float64) * torch.tensor([70.0, 60.0])
    xy = torch.cat([wall, on_axis])
    for cfg in (box, _box(4.0), ellipse):
        _, grad = punch_surface(xy, 12.0, cfg)
        h = 1e-6
        for i in range(2):
            step = torch.zeros(2, dtype=torch.float64)
            step[i] = h
            fd = (punch_surface(xy + step, 12.0, cfg)[0] - punch_surface(xy - step, 12.0, cfg)[0]) / (2 * h)
            torch.testing.assert_close(grad[:, i], fd, rtol=1e-5, atol=1e-6)


def test_a_box_is_drawn_only_when_asked_and_forms():
    default = [sample_part(PartFamily(), seed) for seed in range(50)]
    assert all(p["shape"] != "box" and "dome_exponent" not in p for p in default)
    boxes = [sample_part(PartFamily(shapes=("box",), box_exponent=(4.0, 8.0)), seed) for seed in range(20)]
    assert all(p["shape"] == "box" and p["dome_centre"] == 0.0 for p in boxes)
    assert all(4.0 <= p["dome_exponent"] <= 8.0 for p in boxes)
    family = PartFamily(shapes=("box",), box_exponent=(5.0, 6.0))
    assert PartFamily.from_dict(family.to_dict()) == family and "box_exponent" not in PartFamily().to_dict()
    # a box draws the dome parameters a dome of the same seed draws (its exponent comes after them)
    mixed = sample_part(PartFamily(shapes=("single_dome", "box")), 3)
    dome = sample_part(PartFamily(shapes=("single_dome", "single_dome")), 3)
    assert {k: v for k, v in mixed.items() if k not in ("shape", "dome_exponent")} == {
        k: v for k, v in dome.items() if k != "shape"
    }
    with pytest.raises(ValueError, match="dome_exponent must be >= 2"):
        _box(1.5)
    # a box part simulates: every ply node ends on or above the die (within the contact's give)
    cfg = dataclasses.replace(_box(6.0), num_steps=2)
    traj = simulate_batch(cfg, [0])[0]
    assert torch.isfinite(traj.pos).all()
    ply = traj.ply_mask
    z_die, _ = die_surface(traj.pos[-1, ply, :2].double(), cfg)
    assert (traj.pos[-1, ply, 2].double() - z_die).min() > -0.5 * cfg.ply_thickness


def test_family_settings_are_checked():
    with pytest.raises(ValueError, match="unknown setting"):
        PartFamily.from_dict({"dome_depht": [1, 2]})
    with pytest.raises(ValueError, match="num_plies"):
        PartFamily.from_dict({"num_plies": [3, 2]})
    with pytest.raises(ValueError, match="shapes"):
        PartFamily.from_dict({"shapes": ["hat"]})
    with pytest.raises(ValueError, match="box_exponent"):
        PartFamily.from_dict({"box_exponent": [1.5, 4.0]})
    assert PartFamily.from_dict({"num_plies": [2, 3]}).num_plies == (2, 3)


@pytest.mark.slow
def test_a_family_dataset_gives_every_trajectory_its_part(tmp_path):
    family = PartFamily(num_plies=(2, 3))
    out = tmp_path / "family"
    options = dict(config=TINY, workers=1, compile=False, progress=False)
    paths = generate_dataset(out, 2, 0, 1, family=family, **options)
    assert [p.parent.name for p in paths] == ["train", "train", "test"]
    spec = json.loads((out / "dataset.json").read_text())
    assert spec["family"]["num_plies"] == [2, 3] and spec["simulator"]["ply_cells"] == TINY.ply_cells
    for path in paths:
        traj = Trajectory.load(path)
        seed = traj.meta["seed"]
        part = sample_part(family, seed)
        assert traj.meta["part"]["ply_angles"] == part["ply_angles"]
        assert traj.meta["config"] == part_config(TINY, part).to_dict()
        assert traj.num_components == len(part["ply_angles"]) + 2  # plies, punch, die
        assert torch.isfinite(traj.pos).all()
        # the part has its own random stream: the seed's process setting is the one without a family
        assert torch.equal(traj.gripper_force, sample_process(TINY, seed)[1].float())
    # resumable: nothing left to simulate; another family is refused
    assert generate_dataset(out, 2, 0, 1, family=family, **options) == paths
    with pytest.raises(ValueError, match="another family of parts"):
        generate_dataset(out, 2, 0, 1, family=PartFamily(num_plies=(4, 4)), **options)


@pytest.mark.slow
def test_the_data_cli_makes_a_family_dataset_and_refuses_a_bad_family_file(tmp_path, capsys):
    spec = tmp_path / "family.yaml"
    spec.write_text("num_plies: [2, 2]\nshapes: [single_dome]\n")
    bad = tmp_path / "bad.json"
    bad.write_text('{"num_plies": [2, 2], "colour": "red"}')
    out = tmp_path / "ds"
    assert data_cli.main(["generate", "--out", str(out), "--family", str(bad), "--num-train", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"torch-ampn-data: error: {bad}: not a family of parts") and "colour" in err, err
    assert not out.exists()
    args = ["generate", "--out", str(out), "--family", str(spec), "--num-train", "1", "--num-val", "0"]
    args += ["--num-test", "0", "--workers", "1", "--no-compile", "--simulator", json.dumps(QUICK_SIMULATOR)]
    assert data_cli.main(args) == 0  # 2 plies
    (path,) = sorted((out / "train").glob("*.pt"))
    part = Trajectory.load(path).meta["part"]
    assert part["shape"] == "single_dome" and len(part["ply_angles"]) == 2


def test_the_stack_encoding_counts_plies_per_graph_and_ignores_tool_numbering():
    ply, punch, die = NodeType.PLY, NodeType.PUNCH, NodeType.DIE
    # graph 0: plies 0, 1 and tools 2, 3; graph 1: plies 0, 1, 2 and tools 3, 4
    component = torch.tensor([0, 1, 2, 3, 0, 1, 2, 3, 4])
    node_type = torch.tensor([ply, ply, punch, die, ply, ply, ply, punch, die])
    batch = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 1])
    stack = component_features(component, node_type, 5, "stack", batch)
    expected = [[0, 1], [1, 0], [0, 0], [0, 0], [0, 2], [1, 1], [2, 0], [0, 0], [0, 0]]
    assert stack.tolist() == [[float(v) for v in row] for row in expected]
    swapped = component.clone()  # the tools numbered the other way round: the same features
    swapped[[2, 3, 7, 8]] = torch.tensor([3, 2, 4, 3])
    assert torch.equal(component_features(swapped, node_type, 5, "stack", batch), stack)
    assert not torch.equal(
        component_features(swapped, node_type, 5, "onehot"), component_features(component, node_type, 5)
    )
    alone = component_features(component[4:], node_type[4:], 5, "stack")  # graph 1 on its own
    assert torch.equal(alone, stack[4:])
    traced = torch.compile(component_features, fullgraph=True, backend="eager")  # no graph break
    assert torch.equal(traced(component, node_type, 5, "stack", batch), stack)


def test_a_batch_of_parts_with_other_ply_counts_equals_the_single_predictions():
    family = PartFamily(num_plies=(2, 3))
    seeds = [s for s in range(20) if len(sample_part(family, s)["ply_angles"]) in (2, 3)]
    two = next(s for s in seeds if len(sample_part(family, s)["ply_angles"]) == 2)
    three = next(s for s in seeds if len(sample_part(family, s)["ply_angles"]) == 3)
    cache = HierarchyCache(None, max_levels=2, min_coarse_nodes=4)
    surrogate = AMPNSurrogate(
        num_components=5, num_levels=2, hidden_channels=8, mlp_channels=8, pre_layers=1,
        down_layers=1, solve_layers=1, post_layers=1, up_layers=1, contact_radius=40.0, contact_k=1,
        component_encoding="stack",
    )  # fmt: skip
    windows = []
    for seed in (two, three):
        traj = simulate(part_config(TINY, sample_part(family, seed)), seed=seed)
        windows.append(surrogate.contact(step_sample(traj, 2, cache(traj))))
        surrogate.accumulate_statistics(windows[-1])
    surrogate.freeze_statistics()
    assert windows[0]["l0"].num_nodes != windows[1]["l0"].num_nodes  # two meshes
    noise = [torch.randn(w["l0"].num_nodes, 3, generator=torch.Generator().manual_seed(7)) for w in windows]

    def predict(data, draws):
        x, index, e = surrogate.normalized_features(data)
        it = iter(draws)
        return surrogate.residual_from_features(x, index, e, data["l0"].prev_disp, draw=lambda: next(it))

    with torch.no_grad():
        single = [predict(w, [n]) for w, n in zip(windows, noise, strict=True)]
        batched = predict(Batch.from_data_list(windows), [torch.cat(noise)])
    torch.testing.assert_close(batched, torch.cat(single), atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_every_part_of_a_family_runs_its_own_compiled_step(monkeypatch):
    """Parts with other meshes in one process each compile their solver step: with one entry per
    code object allowed, a shared step would raise at the second part (by default it would run
    the 9th part of a process eagerly, so its last bits would depend on the parts before it)."""
    import torch._dynamo

    from torch_ampn.sim import simulate_batch

    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 1)
    monkeypatch.setattr(torch._dynamo.config, "fail_on_recompile_limit_hit", True)
    family = PartFamily(num_plies=(2, 3))
    parts = [sample_part(family, seed) for seed in (0, 1)]
    configs = [part_config(TINY, part) for part in parts]
    graphs = torch._dynamo.utils.counters["stats"]
    before = graphs["unique_graphs"]
    first, second = (simulate_batch(c, [5], compile=True)[0] for c in configs)
    assert first.num_nodes != second.num_nodes  # other meshes: other compiled steps
    assert graphs["unique_graphs"] - before == 2
    again = simulate_batch(configs[0], [5], compile=True)[0]  # after another part: the same bits
    assert torch.equal(again.pos, first.pos)
    assert graphs["unique_graphs"] - before == 2  # the same mesh again: its compiled step, reused


@pytest.mark.slow
def test_parts_with_one_mesh_but_other_tools_compile_their_own_steps(monkeypatch):
    """Two parts with the same ply count (the same mesh) but other dome geometry: the step reads
    the geometry as constants, so a shared compiled step would recompile for the second part
    (and run a process's 9th such part eagerly); each part gets its own, reused for its seeds."""
    import torch._dynamo

    from torch_ampn.sim import simulate_batch

    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 1)
    monkeypatch.setattr(torch._dynamo.config, "fail_on_recompile_limit_hit", True)
    family = PartFamily(num_plies=(3, 3))
    parts = [sample_part(family, seed) for seed in (10, 11)]  # seeds no other test compiles
    assert parts[0]["dome_axes"] != parts[1]["dome_axes"]
    configs = [part_config(TINY, part) for part in parts]
    graphs = torch._dynamo.utils.counters["stats"]
    before = graphs["unique_graphs"]
    first, second = (simulate_batch(c, [5], compile=True)[0] for c in configs)
    assert first.num_nodes == second.num_nodes  # one mesh, two tool geometries
    assert graphs["unique_graphs"] - before == 2
    again = simulate_batch(configs[0], [6], compile=True)[0]  # another seed of the first part
    assert graphs["unique_graphs"] - before == 2  # its compiled step, reused
    assert again.num_nodes == first.num_nodes


def test_the_example_families_lie_outside_the_default_ranges():
    """examples/families/*.yaml: the test sets beyond the default family that docs/family.md names."""
    from pathlib import Path

    folder = Path(__file__).parents[1] / "examples" / "families"
    default = PartFamily()
    deeper, angle30, box = (data_cli._family(str(folder / f"{n}.yaml")) for n in ("deeper", "angle30", "box"))
    assert deeper.dome_depth[0] >= default.dome_depth[1] and deeper.shapes == default.shapes
    assert not set(angle30.ply_angles) & set(default.ply_angles)
    assert box.shapes == ("box",) and "box" not in default.shapes
    parts = [sample_part(box, seed) for seed in range(5)]
    assert all(p["shape"] == "box" and "dome_exponent" in p for p in parts)
