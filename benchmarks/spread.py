"""Do the process settings matter? The setting spread against the chaos floor, per material.

    python benchmarks/spread.py --seeds 8 --chaos 2 --out benchmarks/results/spread.json
    python benchmarks/spread.py --variants default cfpa6 --seeds 4 --chaos 1   # a quick look

For each material variant (overrides of the simulator's default settings, :data:`VARIANTS`):
``--seeds`` trajectories of random gripper settings (seeds 0, 1, ...), simulated together; the
setting spread (:func:`torch_ampn.sim.spread.setting_spread`: RMSE of each from the mean
trajectory, and between pairs); the chaos floor (:func:`~torch_ampn.sim.spread.chaos_floor`:
the first ``--chaos`` seeds again from a start moved by 1e-6 mm, eager); the substeps per
saved step (the explicit solver's stability limit) and the seconds per trajectory, measured one
variant after the other in this run. Prints a table; writes JSON (atomically) after every
variant, and a rerun skips the variants already in it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path
from typing import Any

import torch

from torch_ampn.sim import StampFormingConfig, simulate_batch
from torch_ampn.sim.config import MATERIAL_V1, PHYSICS_V2
from torch_ampn.sim.simulate import LaminateModel, build_mesh, sample_process
from torch_ampn.sim.spread import chaos_floor, format_report, setting_spread, spread_report
from torch_ampn.utils.io import atomic_write_text

#: The default material until 2026-12-02 (data version 1): far stiffer in transverse tension,
#: in-plane shear and bending than a thermoplastic tape at forming temperature.
V1: dict[str, Any] = dict(MATERIAL_V1)

#: Material variants: overrides of the settings of data version 2 (``PHYSICS_V2`` on
#: StampFormingConfig's defaults; docs/simulator.md, "Material"). The levers of data version 3
#: (viscosity, the contact) are benchmarks/quasi_static.py's.
VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "v1": V1,
    # v1 with less numerical damping
    "damping2": {**V1, "damping": 2.0},
    # towards a CF/PA6 UD tape at forming temperature: matrix-dominated stiffnesses (transverse,
    # in-plane shear, bending) far below the fibres'; still 2-200x above the tape's range
    "matrix20": {"transverse_stiffness": 20.0, "shear_stiffness": 5.0, "bending_stiffness": 100.0},
    "matrix10": {
        "transverse_stiffness": 10.0,
        "shear_stiffness": 2.0,
        "bending_stiffness": 50.0,
        "damping": 5.0,
    },
    # matrix-dominated with the default damping (20 1/s), which holds the plies before contact
    "matrix10_d20": {"transverse_stiffness": 10.0, "shear_stiffness": 2.0, "bending_stiffness": 50.0},
    "matrix5_d20": {"transverse_stiffness": 5.0, "shear_stiffness": 1.0, "bending_stiffness": 25.0},
    # the same with bending at the top of the tape's range (free corners flutter less)
    "matrix5_b50": {"transverse_stiffness": 5.0, "shear_stiffness": 1.0, "bending_stiffness": 50.0},
    # shear at the top of the tape's range (0.5 N/mm), transverse 5 and 2 N/mm
    "shear05_b50": {"transverse_stiffness": 5.0, "shear_stiffness": 0.5, "bending_stiffness": 50.0},
    "matrix2_b50": {"transverse_stiffness": 2.0, "shear_stiffness": 0.5, "bending_stiffness": 50.0},
    # grippers that clamp the nodes within 15 mm (about 1.5 coarse cells) instead of one node
    "v1_clamp15": {**V1, "gripper_clamp_radius": 15.0},
    "matrix20_clamp15": {
        "transverse_stiffness": 20.0,
        "shear_stiffness": 5.0,
        "bending_stiffness": 100.0,
        "gripper_clamp_radius": 15.0,
    },
    "matrix10_clamp15": {
        "transverse_stiffness": 10.0,
        "shear_stiffness": 2.0,
        "bending_stiffness": 50.0,
        "damping": 5.0,
        "gripper_clamp_radius": 15.0,
    },
    # inside the tape's range for transverse and shear
    "matrix2": {
        "transverse_stiffness": 2.0,
        "shear_stiffness": 0.5,
        "bending_stiffness": 10.0,
        "damping": 2.0,
    },
}


def substeps(cfg: StampFormingConfig) -> int:
    """Sub-steps per saved step that the stability limit gives ``cfg``."""
    model = LaminateModel(cfg, build_mesh(cfg), [sample_process(cfg, 0)])
    return int(model.substeps)


def measure(name: str, overrides: dict[str, Any], seeds: int, chaos: int, compile: bool) -> dict[str, Any]:
    """Spread, chaos floor, sub-steps and cost of one variant (``diverged`` where the solver blew up)."""
    cfg = StampFormingConfig.from_dict({**PHYSICS_V2, **overrides})  # the variants of data versions 1-2
    cfg.validate()
    start = time.perf_counter()
    try:
        runs = simulate_batch(cfg, list(range(seeds)), compile=compile)
        seconds = (time.perf_counter() - start) / seeds
        floor = chaos_floor(runs[:chaos])
    except FloatingPointError as err:
        print(f"\n{name} {overrides}: {err}", flush=True)
        diverged = {"diverged": str(err), "trajectories": seeds}
        return {"overrides": overrides, "substeps": substeps(cfg), **diverged}
    report = spread_report(setting_spread(runs), floor)
    print(f"\n{name} {overrides}:\n{format_report(report)}", flush=True)
    return {
        "overrides": overrides,
        "substeps": substeps(cfg),
        "seconds_per_trajectory": seconds,
        "compiled": compile,
        **report,
    }


def table(results: dict[str, Any]) -> str:
    """Markdown table of the variants measured."""
    lines = [
        "| variant | spread from mean [mm] | between pairs [mm] | chaos floor [mm] | spread / floor "
        "| largest motion of a node: in a step; in all [mm] | substeps | s / trajectory |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in results["variants"].items():
        if "diverged" in r:
            lines.append(f"| {name} | {r['diverged']} | | | | | {r['substeps']} | |")
            continue
        blown = " (blown up)" if r["blown_up"] else ""
        lines.append(
            f"| {name} | {r['from_mean']['mean']:.3f} | {r['pairs']['mean']:.3f} | "
            f"{r['chaos_floor']['mean']:.4f} | {r['spread_over_floor']:.1f} | "
            f"{r['max_step_mm']:.1f}; {r['max_displacement_mm']:.0f}{blown} | "
            f"{r['substeps']} | {r['seconds_per_trajectory']:.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument(
        "--variant", action="append", default=[], metavar="NAME=JSON",
        help='another variant, e.g. stiffer=\'{"shear_stiffness": 5}\' (repeatable)',
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, default=8, help="random settings per variant")
    parser.add_argument("--chaos", type=int, default=2, help="of them simulated again, perturbed")
    parser.add_argument("--no-compile", action="store_true", help="eager solver for the spread runs")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/spread.json"))
    args = parser.parse_args(argv)
    if args.seeds < 2 or not 1 <= args.chaos <= args.seeds:
        parser.error("need --seeds >= 2 and 1 <= --chaos <= --seeds")
    variants = {name: VARIANTS[name] for name in args.variants}
    for text in args.variant:
        name, _, spec = text.partition("=")
        try:
            variants[name] = dict(json.loads(spec))
        except (ValueError, TypeError) as err:
            parser.error(f"--variant {text}: not NAME=JSON with a mapping ({err})")
    results: dict[str, Any] = {"variants": {}}
    if args.out.exists():
        results = json.loads(args.out.read_text())
    for name, overrides in variants.items():
        done = results["variants"].get(name)
        if done and done["trajectories"] == args.seeds and done["overrides"] == overrides:
            print(f"{name}: measured before, skipped", flush=True)
            continue
        results["variants"][name] = measure(name, overrides, args.seeds, args.chaos, not args.no_compile)
        results.update(
            date=datetime.date.today().isoformat(),
            machine={"platform": platform.platform(), "threads": torch.get_num_threads()},
        )
        atomic_write_text(args.out, json.dumps(results, indent=1))
    print("\n" + table(results))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
