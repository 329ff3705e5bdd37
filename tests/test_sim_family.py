"""A family of parts: sampled parts, their configurations and a family dataset."""

import json

import pytest
import torch

from torch_ampn import data_cli
from torch_ampn.data import Trajectory
from torch_ampn.sim import PartFamily, StampFormingConfig, generate_dataset, part_config, sample_part
from torch_ampn.sim.geometry import die_surface
from torch_ampn.sim.simulate import sample_process

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


def test_family_settings_are_checked():
    with pytest.raises(ValueError, match="unknown setting"):
        PartFamily.from_dict({"dome_depht": [1, 2]})
    with pytest.raises(ValueError, match="num_plies"):
        PartFamily.from_dict({"num_plies": [3, 2]})
    with pytest.raises(ValueError, match="shapes"):
        PartFamily.from_dict({"shapes": ["box"]})
    assert PartFamily.from_dict({"num_plies": [2, 3]}).num_plies == (2, 3)


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
    args += ["--num-test", "0", "--workers", "1", "--no-compile"]
    assert data_cli.main(args) == 0  # the default (coarse) resolution, 2 plies
    (path,) = sorted((out / "train").glob("*.pt"))
    part = Trajectory.load(path).meta["part"]
    assert part["shape"] == "single_dome" and len(part["ply_angles"]) == 2
