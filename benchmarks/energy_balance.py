"""The simulator's energy balance, data version 2 against the default (data version 3), one setting.

    python benchmarks/energy_balance.py --seed 900000 --plot docs/images/energy_v2_v3.png \\
        --out benchmarks/results/energy_v2_v3.json

Simulates one gripper setting with each physics (eager, float64) and prints the balance's
summary (:func:`torch_ampn.sim.energy.energy_summary`): kinetic over internal energy, the mass
damping's, the viscosity's and friction's dissipation over the external work, the balance's
error; plots both (:func:`torch_ampn.sim.energy.plot_energy`) and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import datetime
import json
from pathlib import Path

from torch_ampn.sim import StampFormingConfig, simulate_batch
from torch_ampn.sim.config import PHYSICS_V2
from torch_ampn.sim.energy import energy_summary, plot_energy
from torch_ampn.utils.io import atomic_write_text

PHYSICS = {"data version 2": PHYSICS_V2, "data version 3": {}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=900_000, help="the gripper setting's seed")
    parser.add_argument("--plot", type=Path, default=Path("docs/images/energy_v2_v3.png"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/energy_v2_v3.json"))
    args = parser.parse_args(argv)
    records, results = [], {}
    for name, overrides in PHYSICS.items():
        traj = simulate_batch(StampFormingConfig(**overrides), [args.seed])[0]
        summary = energy_summary(traj.meta["energy"], name)
        results[name] = {"overrides": overrides, "summary": summary, "energy": traj.meta["energy"]}
        records.append((name, traj.meta["energy"]))
        final = summary["final"]
        print(
            f"{name}: KE/IE median {summary['kinetic_over_internal']:.3f}, peak KE "
            f"{summary['peak_kinetic'] / 1000:.2f} J; external work {final['external'] / 1000:.2f} J "
            f"(grippers {final['work_grippers'] / 1000:.2f} J); dissipated: damping "
            f"{summary['damping_over_work']:.2f}, viscosity {summary['viscosity_over_work']:.2f}, friction "
            f"{summary['friction_over_work']:.2f} of it; balance error {summary['balance_error']:.3f}",
            flush=True,
        )
    plot_energy(records, args.plot, times=traj.time.tolist())
    results["date"] = datetime.date.today().isoformat()
    results["seed"] = args.seed
    atomic_write_text(args.out, json.dumps(results, indent=1))
    print(f"wrote {args.plot} and {args.out}")
    return 0


if __name__ == "__main__":
    from torch_ampn.utils.tuning import enable_cpu_tuning

    enable_cpu_tuning()  # as the command-line programs do (threads follow the free CPU)
    raise SystemExit(main())
