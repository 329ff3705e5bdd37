"""Settings of the embedded quarter double-dome stamp-forming simulator."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

#: Settings added after datasets were first written, with the default that reproduces the
#: physics before them (omitted from :meth:`StampFormingConfig.to_dict` at that value).
ADDED_LATER: dict[str, Any] = {
    "gripper_clamp_radius": 0.0,
    "matrix_viscosity": 0.0,
    "bending_viscosity": 0.0,
    "contact_damping": 0.0,
    "ply_contact": "node",
    "selective_mass_scaling": False,
    "dome_exponent": 2.0,
}
#: The default physics of data version 2 (2026-12-02 to 2026-12-05): mass-proportional damping
#: only, ply on ply against the nearest node's plane. With the material of its day
#: (``StampFormingConfig(**PHYSICS_V2)``, or ``--simulator`` with them) it remakes data of then.
PHYSICS_V2: dict[str, Any] = {
    "damping": 20.0,
    "matrix_viscosity": 0.0,
    "bending_viscosity": 0.0,
    "ply_contact": "node",
}
#: The default material until 2026-12-02 (data version 1): pass these to reproduce data made
#: before, with the physics of then, e.g. ``StampFormingConfig(**MATERIAL_V1, **PHYSICS_V2)``.
MATERIAL_V1: dict[str, float] = {
    "transverse_stiffness": 100.0,
    "shear_stiffness": 20.0,
    "bending_stiffness": 500.0,
}


@dataclass
class StampFormingConfig:
    """Process, geometry, material and solver settings (units: mm, N, s).

    The defaults give the coarse model used by tests and the quickstart (16 x 16 x 2
    triangles per ply); :meth:`paper` gives the seed paper's resolution (3,200 triangles per
    ply, 4,290-quad punch, 5,100-quad die).

    Geometry: a quarter of a double-dome part, cut along the symmetry planes e1 = 0 and
    e2 = 0. Plies cover ``[0, ply_size[0]] x [0, ply_size[1]]``, stacked ``ply_thickness``
    apart starting at e3 = 0, on a fixed die. The punch moves ``stroke`` mm down along e3
    over ``duration`` s; its dome apex starts ``punch_clearance`` mm above the stack. A dome's
    footprint is the superellipse ``|x / a|^p + |y / b|^p = 1`` of its semi-axes ``dome_axes``
    with ``p = dome_exponent``: 2 is an ellipse, larger values square it off towards a rounded
    box (the punch of a box or hat section).

    Grippers: each pulls its anchor-ward force ``gripper_force_range`` through all plies: on
    the node nearest its point in every ply (``gripper_clamp_radius = 0``: a needle), or, with
    a clamp radius (mm), on every node of each ply within that distance of it, the force shared
    equally and each node pulled towards the anchor shifted by its offset (a rigid clamp).

    Dynamics: explicit (semi-implicit Euler) time integration with lumped nodal masses
    ``areal_mass`` (t/mm^2, i.e. N s^2/mm^3; scaled up from the physical ~1e-9, as explicit
    FEM codes do), mass-proportional viscous ``damping`` (1/s), which resists every motion, and
    the damping of deformation only: ``matrix_viscosity`` (N s/mm, a Kelvin-Voigt stress on the
    transverse and shear strain rates: the molten matrix) and ``bending_viscosity`` (N mm s, on
    the bending rate); ``contact_damping`` damps the normal motion of closed penalty contacts,
    as a fraction of the critical damping of the penalty spring on the node's mass (explicit
    codes' contact damping, against chatter). Ply on ply, ``ply_contact = "node"`` keeps each
    node of a ply off the tangent plane of the nearest node of the ply below (partners chosen
    at every saved step; the penalty cut off past two thicknesses), ``"face"`` off the closest
    of the triangles around that node, the reaction shared by the face's nodes and the penalty
    faded out continuously (conservative in the gap). ``selective_mass_scaling`` adds mass to
    the nodes whose stability limit is shorter than the median node's (the light edge and corner
    nodes), as explicit codes scale mass to a target time step. ``substeps`` per saved
    step is chosen from the stability limit (``time_step_safety`` times the critical step)
    when ``None``; a fixed value that is unstable is refused. The physics does not depend
    on ``substeps``, so refining it converges.
    """

    # discretisation
    ply_cells: int = 16
    punch_cells: tuple[int, int] = (14, 14)
    die_cells: tuple[int, int] = (16, 16)
    num_steps: int = 50
    substeps: int | None = None

    # geometry
    ply_size: tuple[float, float] = (150.0, 150.0)
    ply_angles: tuple[float, ...] = (0.0, 45.0, 90.0, -45.0)
    ply_thickness: float = 0.5
    tool_size: tuple[float, float] = (165.0, 165.0)
    dome_depth: float = 50.0
    dome_centre: float = 55.0
    dome_axes: tuple[float, float] = (70.0, 60.0)
    dome_flat_top: float = 0.35
    dome_exponent: float = 2.0
    die_clearance: float = 3.0

    # process
    stroke: float = 60.0
    duration: float = 1.0
    punch_clearance: float = 10.0
    num_grippers: int = 2
    gripper_force_range: tuple[float, float] = (0.0, 100.0)
    gripper_position_range: tuple[float, float] = (0.15, 0.85)
    gripper_anchor_distance: float = 80.0
    gripper_clamp_radius: float = 0.0

    # material and contact (effective values; the mass is scaled up, as in explicit FEM,
    # so that the explicit time step stays affordable). A matrix-dominated ply, towards a
    # CF/PA6 UD tape at forming temperature (docs/simulator.md, "Material"); until 2026-12-02
    # (data version 1) transverse 100, shear 20 N/mm and bending 500 N mm
    fiber_stiffness: float = 2000.0
    transverse_stiffness: float = 5.0
    shear_stiffness: float = 1.0
    compression_ratio: float = 0.2
    bending_stiffness: float = 50.0
    contact_stiffness: float = 2000.0
    friction_tool: float = 0.3
    friction_ply: float = 0.2
    areal_mass: float = 6e-6
    # the deformation damped by the matrix's and the bending's viscosity, rigid motion little by
    # the mass; ply on ply against the closest face (data version 3, since 2026-12-05; until
    # then, data version 2: PHYSICS_V2)
    damping: float = 2.0
    matrix_viscosity: float = 0.2
    bending_viscosity: float = 2.0
    contact_damping: float = 0.0
    ply_contact: str = "face"
    selective_mass_scaling: bool = False
    time_step_safety: float = 0.6

    meta: dict = field(default_factory=dict)

    @classmethod
    def paper(cls, **overrides) -> StampFormingConfig:
        """The seed paper's resolution: 40 x 40 x 2 triangles per ply, 66 x 65 punch and 75 x 68 die quads."""
        values = dict(ply_cells=40, punch_cells=(66, 65), die_cells=(75, 68))
        values.update(overrides)
        return cls(**values)

    @classmethod
    def from_dict(
        cls, values: Mapping[str, Any], base: StampFormingConfig | None = None
    ) -> StampFormingConfig:
        """Settings from a plain ``dict``, e.g. of JSON or YAML (the inverse of :meth:`to_dict`).

        Lists become tuples. Settings missing from ``values`` are those of ``base`` (default:
        the defaults), except in a complete record (every setting that is not in
        :data:`ADDED_LATER`: what :meth:`to_dict` wrote, e.g. in an older dataset's
        ``dataset.json``), where a missing setting added later takes the value that reproduces
        the physics before it. The result is not validated (see :meth:`validate`).

        Args:
            values: Setting name -> value.
            base: The settings that ``values`` override.

        Raises:
            TypeError: If ``values`` is not a mapping.
            ValueError: For keys that are not settings (the message names them).
        """
        if not isinstance(values, Mapping):
            raise TypeError(f"StampFormingConfig: settings must be a mapping, got {type(values).__name__}")
        unknown = sorted(str(k) for k in set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"StampFormingConfig: unknown setting(s) {', '.join(map(repr, unknown))}")
        merged = {**base.to_dict(), **values} if base is not None else dict(values)
        recorded = {f.name for f in fields(cls)} - set(ADDED_LATER) - {"meta"}
        if base is None and recorded <= set(values):  # a complete record: written before some settings
            merged = {**{k: v for k, v in ADDED_LATER.items() if k not in values}, **merged}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in merged.items()})

    @property
    def num_plies(self) -> int:
        """Number of plies ``P``."""
        return len(self.ply_angles)

    def to_dict(self) -> dict:
        """Plain ``dict`` (stored in the trajectory's ``meta``).

        Settings added after datasets were first written (:data:`ADDED_LATER`) appear only
        when they differ from their default, so that the settings of older files and of new
        ones with the same physics are the same dict.
        """
        values = asdict(self)
        for name, default in ADDED_LATER.items():
            if values[name] == default:
                del values[name]
        return values

    def validate(self) -> None:
        """Raise ``ValueError`` for settings the simulator cannot run."""
        checks = [
            (self.ply_cells >= 2, "ply_cells must be >= 2"),
            (min(self.punch_cells) >= 1 and min(self.die_cells) >= 1, "tool cells must be >= 1"),
            (self.num_steps >= 1, "num_steps must be >= 1"),
            (self.substeps is None or self.substeps >= 1, "substeps must be None (automatic) or >= 1"),
            (self.areal_mass > 0, "areal_mass must be positive"),
            (0 < self.time_step_safety <= 1, "time_step_safety must be in (0, 1]"),
            (self.num_plies >= 1, "ply_angles must list at least one ply"),
            (self.ply_thickness > 0, "ply_thickness must be positive"),
            (0 <= self.gripper_force_range[0] <= self.gripper_force_range[1], "bad gripper_force_range"),
            (
                0 <= self.gripper_position_range[0] <= self.gripper_position_range[1] <= 1,
                "bad gripper_position_range",
            ),
            (self.num_grippers in (0, 1, 2), "num_grippers must be 0, 1 or 2 (one per free edge)"),
            (self.duration > 0 and self.stroke >= 0, "duration must be positive and stroke non-negative"),
            (0 < self.dome_flat_top < 1, "dome_flat_top must be in (0, 1)"),
            (self.dome_exponent >= 2, "dome_exponent must be >= 2 (2: an ellipse, more: a rounded box)"),
            (self.damping >= 0, "damping must be non-negative"),
            (self.matrix_viscosity >= 0, "matrix_viscosity must be non-negative"),
            (0 <= self.contact_damping <= 1, "contact_damping must be a fraction of critical in [0, 1]"),
            (self.ply_contact in ("node", "face"), "ply_contact must be 'node' or 'face'"),
            (
                self.bending_viscosity == 0 or (self.bending_viscosity > 0 and self.bending_stiffness > 0),
                "bending_viscosity must be non-negative, and positive only with a positive bending_stiffness",
            ),
            (self.gripper_clamp_radius >= 0, "gripper_clamp_radius must be non-negative"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"StampFormingConfig: {msg}")
