"""The simulator's energy balance, as explicit FEM codes report it.

Every simulated trajectory keeps, in ``meta["energy"]``, one value per saved step (N mm = mJ)
of each term below; Abaqus's names in brackets:

* state: ``kinetic`` (ALLKE), ``membrane`` and ``bending`` strain energy (their sum: ALLIE's
  strain energy, ALLSE), ``contact`` penalty energy of the tool and ply-on-ply contacts;
* path, summed over the solver's sub-steps from the start: ``damping``, the mass-proportional
  damping's dissipation (ALLVD), ``viscosity``, the matrix and bending viscosity's dissipation
  (the material's, ALLCD in a viscous material), ``friction`` (ALLFD), ``walls``, the kinetic
  energy the symmetry planes remove from nodes they stop, and the external work (ALLWK) of the
  ``work_grippers`` and of the ``work_punch`` (its contact and friction forces on the plies).

The balance ``kinetic + membrane + bending + contact + damping + viscosity + friction + walls -
work_grippers - work_punch`` (ETOTAL) stays near zero: its drift is the time integration's error.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

#: Energies of the state at each saved step, in the order of ``LaminateModel.state_energies``.
STATE_TERMS: tuple[str, ...] = ("kinetic", "membrane", "bending", "contact")
#: Path terms summed over the sub-steps, in the order of the solver step's ``work``.
WORK_TERMS: tuple[str, ...] = ("damping", "viscosity", "friction", "walls", "work_grippers", "work_punch")
TERMS: tuple[str, ...] = STATE_TERMS + WORK_TERMS
#: The quasi-static regime's practice: kinetic energy at most this fraction of the internal energy.
KINETIC_OVER_INTERNAL = 0.05
#: And numerical (mass-proportional) damping at most this fraction of the external work.
DAMPING_OVER_WORK = 0.10


def energy_record(values: Tensor) -> dict[str, list[float]]:
    """``meta["energy"]`` of one trajectory from its terms ``[T+1, len(TERMS)]`` (N mm)."""
    if values.dim() != 2 or values.size(1) != len(TERMS):
        raise ValueError(f"energy terms must be [T+1, {len(TERMS)}], got {list(values.shape)}")
    return {name: values[:, i].tolist() for i, name in enumerate(TERMS)}


def energy_table(record: Mapping[str, Sequence[float]], source: str = "meta") -> dict[str, Tensor]:
    """The terms of ``record`` as float64 tensors ``[T+1]``, with the sums of the balance.

    Adds ``internal`` (membrane + bending), ``external`` (the grippers' and the punch's work),
    ``dissipated`` (damping, viscosity, friction, walls) and ``balance`` (ETOTAL).

    Raises:
        ValueError: naming ``source`` and the missing or ragged field.
    """
    missing = [name for name in TERMS if name not in record]
    if missing:
        raise ValueError(f"{source}: field 'energy' lacks {', '.join(missing)}")
    out = {name: torch.as_tensor(record[name], dtype=torch.float64) for name in TERMS}
    lengths = {v.numel() for v in out.values()}
    if len(lengths) != 1:
        raise ValueError(f"{source}: field 'energy' has terms of different lengths {sorted(lengths)}")
    out["internal"] = out["membrane"] + out["bending"]
    out["external"] = out["work_grippers"] + out["work_punch"]
    out["dissipated"] = out["damping"] + out["viscosity"] + out["friction"] + out["walls"]
    out["balance"] = out["kinetic"] + out["internal"] + out["contact"] + out["dissipated"] - out["external"]
    return out


def energy_summary(record: Mapping[str, Sequence[float]], source: str = "meta") -> dict[str, Any]:
    """Scalars of one trajectory's balance: is it quasi-static, and where did the work go?

    ``kinetic_over_internal``: the median over the saved steps after the first (where the
    internal energy is positive) of kinetic over internal energy, and ``quasi_static_fraction``:
    the fraction of those steps at most :data:`KINETIC_OVER_INTERNAL`; the final values (N mm)
    of every term; ``damping_over_work`` and ``viscosity_over_work``: the final dissipations over
    the final external work; ``balance_error``: the largest ``|balance|`` over the steps, relative
    to the final external work.
    """
    t = energy_table(record, source)
    steps = slice(1, None)
    internal, kinetic = t["internal"][steps], t["kinetic"][steps]
    active = internal > 0
    ratio = kinetic[active] / internal[active]
    work = float(t["external"][-1])
    scale = work if abs(work) > 0 else float("nan")
    return {
        "kinetic_over_internal": float(ratio.median()) if ratio.numel() else float("nan"),
        "peak_kinetic": float(t["kinetic"].max()),
        "quasi_static_fraction": float((ratio <= KINETIC_OVER_INTERNAL).double().mean())
        if ratio.numel()
        else 0.0,
        "damping_over_work": float(t["damping"][-1]) / scale,
        "viscosity_over_work": float(t["viscosity"][-1]) / scale,
        "friction_over_work": float(t["friction"][-1]) / scale,
        "balance_error": float(t["balance"].abs().max()) / abs(scale),
        "final": {name: float(t[name][-1]) for name in (*TERMS, "internal", "external")},
    }


def plot_energy(
    records: Sequence[tuple[str, Mapping[str, Sequence[float]]]],
    path: str | Path,
    times: Sequence[float] | None = None,
) -> Path:
    """Plot each ``(label, meta["energy"])``: the terms over time, and the two ratios of the regime.

    Left: kinetic, internal, contact, the dissipations and the external work (J); middle:
    kinetic over internal energy with the :data:`KINETIC_OVER_INTERNAL` line; right: damping
    over external work with :data:`DAMPING_OVER_WORK`. Written atomically as PNG.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_ampn.utils.io import atomic_savefig

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    styles = ["-", "--", ":", "-."]
    for r, (label, record) in enumerate(records):
        t = energy_table(record, label)
        x = (
            torch.as_tensor(times, dtype=torch.float64)
            if times is not None
            else torch.arange(t["kinetic"].numel())
        )
        ls = styles[r % len(styles)]
        for name, colour in (
            ("kinetic", "C0"),
            ("internal", "C1"),
            ("contact", "C2"),
            ("damping", "C3"),
            ("viscosity", "C4"),
            ("friction", "C5"),
            ("external", "k"),
        ):
            axes[0].plot(x, t[name] / 1000.0, ls, color=colour, label=name if r == 0 else None)
        internal = t["internal"].clamp_min(1e-9)
        axes[1].semilogy(x[1:], (t["kinetic"] / internal)[1:], ls, color="C0", label=label)
        work = t["external"].clamp_min(1e-9)
        axes[2].plot(x[1:], (t["damping"] / work)[1:], ls, color="C3", label=label)
    names = {"-": "solid", "--": "dashed", ":": "dotted", "-.": "dash-dotted"}
    key = ", ".join(f"{names[styles[r % len(styles)]]}: {label}" for r, (label, _) in enumerate(records))
    axes[0].set_title(key, fontsize=8)
    axes[0].set(xlabel="time [s]" if times is not None else "saved step", ylabel="energy [J]")
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].axhline(KINETIC_OVER_INTERNAL, color="grey", lw=0.8)
    axes[1].set(xlabel=axes[0].get_xlabel(), ylabel="kinetic / internal energy")
    axes[1].legend(fontsize=7)
    axes[2].axhline(DAMPING_OVER_WORK, color="grey", lw=0.8)
    axes[2].set(xlabel=axes[0].get_xlabel(), ylabel="damping dissipation / external work")
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


__all__ = [
    "DAMPING_OVER_WORK",
    "KINETIC_OVER_INTERNAL",
    "STATE_TERMS",
    "TERMS",
    "WORK_TERMS",
    "energy_record",
    "energy_summary",
    "energy_table",
    "plot_energy",
]
