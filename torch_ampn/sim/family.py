"""A family of parts: tool geometry and ply stack sampled per trajectory, for one model of many parts.

A :class:`PartFamily` holds the ranges; :func:`sample_part` draws one part from them for a
seed (reproducibly, from its own random stream, so the process setting that
:func:`~torch_ampn.sim.simulate` draws for the same seed is not changed by it) and
:func:`part_config` turns it into the :class:`~torch_ampn.sim.StampFormingConfig` of that
part. Every trajectory of a family dataset records its part in ``meta["part"]`` (and its
whole configuration in ``meta["config"]``, as every simulated trajectory does).

Punch shapes the tool description expresses (all flat-topped and smoothly blended, see
:mod:`torch_ampn.sim.geometry`):

* ``"double_dome"``: two elliptic domes at ``(+-dome_centre, 0)``, the seed paper's part (the
  quarter model sees one dome and half of the saddle);
* ``"single_dome"``: one elliptic dome at the origin (``dome_centre = 0``; the quarter model
  sees a quarter of it);
* ``"box"``: one rounded box at the origin, the punch of a box section: its footprint is the
  superellipse of exponent ``dome_exponent``, drawn from ``box_exponent``. A family draws it
  only when asked (it is not in :class:`PartFamily`'s default ``shapes``), so that a model of
  the domes can be tested on a tool shape it never saw.

The stroke follows the depth (``punch_clearance + dome_depth``: the punch closes on the die at
the end of every process).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch

from torch_ampn.sim.config import StampFormingConfig

#: Punch shapes a family can draw.
SHAPES = ("double_dome", "single_dome", "box")

#: Offset of the part's random stream from the process's (``sample_process`` uses the seed itself).
PART_STREAM = 0x5EED_0000


@dataclass
class PartFamily:
    """Ranges of the parts of a family (units: mm, degrees). Ranges are ``(low, high)``, inclusive.

    Args:
        dome_depth: Depth of the domes.
        dome_axis_x: Semi-axis of a dome along e1.
        dome_axis_y: Semi-axis of a dome along e2.
        dome_centre: Distance of the two domes' centres from the symmetry plane e1 = 0
            (``"double_dome"`` only).
        dome_flat_top: Flat top of a dome as a fraction of its semi-axes.
        shapes: Punch shapes to draw from, equally likely (:data:`SHAPES`; the domes by default).
        box_exponent: Exponent of a box's superellipse footprint (``"box"`` only; 2 would be an
            ellipse).
        num_plies: Fewest and most plies of a stack.
        ply_angles: Fibre angles a ply draws from, equally likely and independently per ply.
    """

    dome_depth: tuple[float, float] = (40.0, 55.0)
    dome_axis_x: tuple[float, float] = (60.0, 75.0)
    dome_axis_y: tuple[float, float] = (50.0, 65.0)
    dome_centre: tuple[float, float] = (45.0, 60.0)
    dome_flat_top: tuple[float, float] = (0.25, 0.45)
    shapes: tuple[str, ...] = ("double_dome", "single_dome")
    box_exponent: tuple[float, float] = (4.0, 8.0)
    num_plies: tuple[int, int] = (2, 6)
    ply_angles: tuple[float, ...] = (0.0, 45.0, 90.0, -45.0)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> PartFamily:
        """A family from a plain ``dict`` (YAML/JSON; lists become tuples); unknown keys are refused."""
        if not isinstance(values, Mapping):
            raise TypeError(f"PartFamily: settings must be a mapping, got {type(values).__name__}")
        unknown = sorted(str(k) for k in set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"PartFamily: unknown setting(s) {', '.join(map(repr, unknown))}")
        family = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
        family.validate()
        return family

    def to_dict(self) -> dict[str, Any]:
        """Plain ``dict`` (stored in ``dataset.json``).

        ``box_exponent`` only for a family with boxes: a family of domes is the dict it was before.
        """
        values = asdict(self)
        if "box" not in self.shapes:
            del values["box_exponent"]
        return values

    def validate(self) -> None:
        """``ValueError`` naming the first setting that cannot make parts."""
        for name in ("dome_depth", "dome_axis_x", "dome_axis_y", "dome_centre", "dome_flat_top"):
            low, high = getattr(self, name)
            if not (math.isfinite(low) and math.isfinite(high) and 0 <= low <= high):
                raise ValueError(f"PartFamily: {name} must be a range 0 <= low <= high, got {(low, high)}")
        low, high = self.box_exponent
        if not (math.isfinite(high) and 2 <= low <= high):
            raise ValueError(f"PartFamily: box_exponent must be a range 2 <= low <= high, got {(low, high)}")
        if not (0 < self.dome_flat_top[0] and self.dome_flat_top[1] < 1):
            raise ValueError(f"PartFamily: dome_flat_top must lie in (0, 1), got {self.dome_flat_top}")
        if not self.shapes or any(s not in SHAPES for s in self.shapes):
            raise ValueError(f"PartFamily: shapes must be a non-empty subset of {SHAPES}, got {self.shapes}")
        low, high = self.num_plies
        if not (isinstance(low, int) and isinstance(high, int) and 1 <= low <= high):
            raise ValueError(f"PartFamily: num_plies must be a range 1 <= low <= high, got {self.num_plies}")
        if not self.ply_angles:
            raise ValueError("PartFamily: ply_angles must list at least one angle")


def sample_part(family: PartFamily, seed: int) -> dict[str, Any]:
    """The part of ``seed``: shape, dome dimensions and ply stack, drawn from ``family``'s ranges.

    Returns:
        ``{"shape", "dome_depth", "dome_axes", "dome_centre", "dome_flat_top", "ply_angles"}``
        (``dome_centre`` is 0 for a single dome and a box), and a box's ``"dome_exponent"``
        (drawn after the rest, so that the domes of a family draw what they drew before boxes).
    """
    g = torch.Generator().manual_seed(PART_STREAM + int(seed))

    def uniform(bounds: tuple[float, float]) -> float:
        low, high = bounds
        return low + (high - low) * float(torch.rand((), generator=g, dtype=torch.float64))

    def choice(options: Sequence) -> Any:
        return options[int(torch.randint(len(options), (), generator=g))]

    shape = choice(family.shapes)
    depth = uniform(family.dome_depth)
    axes = (uniform(family.dome_axis_x), uniform(family.dome_axis_y))
    centre = uniform(family.dome_centre)
    flat = uniform(family.dome_flat_top)
    plies = int(torch.randint(family.num_plies[0], family.num_plies[1] + 1, (), generator=g))
    angles = tuple(float(choice(family.ply_angles)) for _ in range(plies))
    part = {
        "shape": shape,
        "dome_depth": depth,
        "dome_axes": axes,
        "dome_centre": centre if shape == "double_dome" else 0.0,
        "dome_flat_top": flat,
        "ply_angles": angles,
    }
    if shape == "box":
        part["dome_exponent"] = uniform(family.box_exponent)
    return part


def part_config(base: StampFormingConfig, part: Mapping[str, Any]) -> StampFormingConfig:
    """``base`` with the part's tool geometry and ply stack (the stroke closes the tools at the end)."""
    values = {k: v for k, v in part.items() if k != "shape"}
    values["dome_axes"] = tuple(values["dome_axes"])
    values["ply_angles"] = tuple(values["ply_angles"])
    values["stroke"] = base.punch_clearance + float(values["dome_depth"])
    cfg = StampFormingConfig.from_dict(values, base=base)
    cfg.validate()
    return cfg
