"""Do the process settings decide the part? The levers of a quasi-static forming, side by side.

    python benchmarks/quasi_static.py --out benchmarks/results/quasi_static.json
    python benchmarks/quasi_static.py --variants v2 visc1 --settings 6     # a quick look

For each variant (overrides of data version 2's settings, :data:`VARIANTS`): ``--settings``
gripper settings of seeds no dataset uses (900000, 900001, ...), simulated twice as one batch
each, the second time from a start moved by up to 1e-6 mm (both batches compiled, of the same
size, so they differ by the perturbation alone); then

* the setting spread (RMSE of each run from the mean run) and the chaos (RMSE between the two
  runs of a setting), :mod:`torch_ampn.sim.spread`;
* the two-run reliability of the part-quality measures (Spearman of the two runs over the
  settings, spread between settings over spread within one), ``two_run_reliability``;
* the energy balance (:mod:`torch_ampn.sim.energy`): kinetic over internal energy, the
  mass-proportional damping's and the viscosity's dissipation over the external work, the
  balance's error; medians over the runs;
* blown-up runs, sub-steps per saved step, seconds per trajectory (the first batch, its
  compile included, one variant after the other in this run).

Prints a table; writes JSON atomically after every variant; a rerun skips what it holds.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from torch_ampn.sim import StampFormingConfig, simulate_batch
from torch_ampn.sim.config import PHYSICS_V2
from torch_ampn.sim.energy import energy_summary
from torch_ampn.sim.spread import blow_up, format_reliability, setting_spread, two_run_reliability
from torch_ampn.utils.io import atomic_write_text

#: First seed of the settings: no dataset split uses it (train 0.., val 100000.., test 200000..).
FIRST_SEED = 900_000

#: Overrides of the settings of data version 2 (``PHYSICS_V2`` on StampFormingConfig's defaults, the
#: default until 2026-12-05); "face_visc02" is data version 3's default.
VISC02: dict[str, Any] = {"damping": 2.0, "matrix_viscosity": 0.2, "bending_viscosity": 2.0}
VISC05: dict[str, Any] = {"damping": 2.0, "matrix_viscosity": 0.5, "bending_viscosity": 5.0}
FACE: dict[str, Any] = {"ply_contact": "face"}
VARIANTS: dict[str, dict[str, Any]] = {
    "v2": {},
    # deformation damped by the molten matrix's and the bending's viscosity, rigid motion less by the mass
    "visc02": VISC02,
    "visc05": VISC05,
    # ply-on-ply contact against the closest face, conservative in the gap (no energy made by the contact)
    "face": FACE,
    "face_visc02": {**FACE, **VISC02},
    "face_visc05": {**FACE, **VISC05},
    # bending at 10 N mm (inside the tape's range, a fifth of v2's): room for wrinkles
    "face_b10": {**FACE, "bending_stiffness": 10.0},
    "face_visc02_b10": {**FACE, **VISC02, "bending_stiffness": 10.0, "bending_viscosity": 0.4},
    # half the mass scaling (the sub-step, and the cost, 1.4 times)
    "face_mass2_visc02": {**FACE, **VISC02, "areal_mass": 3e-6},
    # data version 3 with contact damping (a fifth of critical: against chatter in the closed contacts)
    "face_visc02_cd02": {**FACE, **VISC02, "contact_damping": 0.2},
    # data version 3 on a finer ply mesh (6.25 mm cells instead of 9.4 mm): room for wrinkles
    "face_visc02_cells24": {**FACE, **VISC02, "ply_cells": 24},
}


def _median(values: list[float]) -> float:
    finite = [v for v in values if v == v]
    return statistics.median(finite) if finite else float("nan")


def measure(name: str, overrides: dict[str, Any], settings: int) -> dict[str, Any]:
    """Spread, chaos, reliability, energy balance and cost of one variant."""
    cfg = StampFormingConfig.from_dict({**PHYSICS_V2, **overrides})
    cfg.validate()
    seeds = list(range(FIRST_SEED, FIRST_SEED + settings))
    start = time.perf_counter()
    try:
        first = simulate_batch(cfg, seeds, compile=True)
        seconds = (time.perf_counter() - start) / settings
        second = simulate_batch(cfg, seeds, compile=True, perturbation=1e-6)
    except FloatingPointError as err:
        print(f"\n{name} {overrides}: {err}", flush=True)
        return {"overrides": overrides, "settings": settings, "diverged": str(err)}
    blown = [reason for t in (*first, *second) if (reason := blow_up(t))]
    spread = setting_spread(first)
    reliability = two_run_reliability(first, second)
    energies = [energy_summary(t.meta["energy"]) for t in first]
    energy = {
        key: _median([e[key] for e in energies])
        for key in (
            "kinetic_over_internal",
            "quasi_static_fraction",
            "damping_over_work",
            "viscosity_over_work",
            "friction_over_work",
            "balance_error",
            "peak_kinetic",
        )
    }
    energy["external_work"] = _median([e["final"]["external"] for e in energies])
    energy["work_grippers"] = _median([e["final"]["work_grippers"] for e in energies])
    result = {
        "overrides": overrides,
        "settings": settings,
        "substeps": int(first[0].meta["substeps"]),
        "seconds_per_trajectory": seconds,
        "spread_mm": spread["from_mean"]["mean"],
        "chaos_mm": reliability["chaos_mm"]["mean"],
        "blown_up": blown,
        "reliability": reliability,
        "energy": energy,
    }
    print(f"\n{name} {overrides}: {len(blown)} blown up; energy {json.dumps(energy)}")
    print(format_reliability(reliability), flush=True)
    return result


def table(results: dict[str, Any]) -> str:
    """Markdown table of the variants measured."""
    lines = [
        "| variant | spread [mm] | chaos [mm] | spread / chaos | Spearman draw-in / wrinkle RMS / shear RMS "
        "| wrinkle between / within | wrinkle RMS range [mm] | draw-in range [mm] | KE / IE | damping / work "
        "| blown up | substeps | s / trajectory |",
        "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in results["variants"].items():
        if "diverged" in r:
            lines.append(f"| {name} | {r['diverged']} |" + " |" * 12)
            continue
        m, e = r["reliability"]["measures"], r["energy"]
        lines.append(
            f"| {name} | {r['spread_mm']:.2f} | {r['chaos_mm']:.3f} | {r['spread_mm'] / r['chaos_mm']:.1f} | "
            f"{m['draw_in_mean']['spearman']:.2f} / {m['wrinkle_rms']['spearman']:.2f} / "
            f"{m['shear_rms']['spearman']:.2f} | {m['wrinkle_rms']['between_over_within']:.1f} | "
            f"{m['wrinkle_rms']['range']:.3f} | {m['draw_in_mean']['range']:.2f} | "
            f"{e['kinetic_over_internal']:.3f} | {e['damping_over_work']:.2f} | {len(r['blown_up'])} | "
            f"{r['substeps']} | {r['seconds_per_trajectory']:.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument(
        "--variant", action="append", default=[], metavar="NAME=JSON",
        help='another variant, e.g. soft=\'{"shear_stiffness": 0.5}\' (repeatable)',
    )  # fmt: skip
    parser.add_argument("--settings", type=int, default=12, help="gripper settings per variant (>= 3)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/quasi_static.json"))
    args = parser.parse_args(argv)
    if args.settings < 3:
        parser.error("need --settings >= 3 (a rank correlation over the settings)")
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
        if done and done["settings"] == args.settings and done["overrides"] == overrides:
            print(f"{name}: measured before, skipped", flush=True)
            continue
        results["variants"][name] = measure(name, overrides, args.settings)
        results.update(
            date=datetime.date.today().isoformat(),
            machine={
                "platform": platform.platform(),
                "processor": platform.processor(),
                "threads": torch.get_num_threads(),
            },
        )
        atomic_write_text(args.out, json.dumps(results, indent=1))
    print("\n" + table(results))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
