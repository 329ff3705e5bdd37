"""The embedded stamp-forming simulator: explicit, damped, vectorised (PyTorch), deterministic.

Several process settings are simulated at once as one disjoint system (``B`` copies of
the laminate), which amortises PyTorch's per-operation overhead; ``compile=True`` runs the
force evaluation through ``torch.compile`` for another several-fold speed-up.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torch_ampn.data.mesh import MultiComponentMesh, rectangle_mesh
from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.sim.config import StampFormingConfig
from torch_ampn.sim.contact import (
    contact_damping,
    face_plane,
    faded_penalty,
    height_field_contact,
    incident_faces,
    nearest_nodes,
    ply_on_face_contact,
    ply_on_face_gap,
    ply_on_ply_contact,
    ply_on_ply_normal,
    smooth_friction,
    vertex_normals,
)
from torch_ampn.sim.energy import WORK_TERMS, energy_record
from torch_ampn.sim.geometry import die_surface, punch_surface, punch_travel
from torch_ampn.sim.mechanics import OrthotropicMembrane, QuadraticBending
from torch_ampn.utils.own_code import own_code
from torch_ampn.utils.threads import follow_free_cpu


def build_mesh(cfg: StampFormingConfig) -> MultiComponentMesh:
    """Plies (triangles), punch and die (quads) of the quarter model, in their initial positions (float64)."""
    parts = []
    for k in range(cfg.num_plies):
        pos, cells = rectangle_mesh(
            cfg.ply_cells, cfg.ply_cells, cfg.ply_size, (0.0, 0.0, k * cfg.ply_thickness), dtype=torch.float64
        )
        parts.append((f"ply{k}", pos, cells, NodeType.PLY))
    for name, cells_xy, surface, node_type in (
        ("punch", cfg.punch_cells, lambda xy: punch_surface(xy, 0.0, cfg)[0], NodeType.PUNCH),
        ("die", cfg.die_cells, lambda xy: die_surface(xy, cfg)[0], NodeType.DIE),
    ):
        pos, cells = rectangle_mesh(
            cells_xy[0], cells_xy[1], cfg.tool_size, cell_type="quad", dtype=torch.float64
        )
        pos[:, 2] = surface(pos[:, :2])
        parts.append((name, pos, cells, node_type))
    return MultiComponentMesh.merge(parts)


def sample_process(cfg: StampFormingConfig, seed: int) -> tuple[Tensor, Tensor]:
    """Gripper positions (fraction along their edge) and pulling forces (N) for ``seed``, ``[G]`` each.

    Gripper 0 sits on the free edge e1 = ply_size[0], gripper 1 on the free edge e2 = ply_size[1].
    """
    generator = torch.Generator().manual_seed(seed)
    lo, hi = cfg.gripper_position_range
    flo, fhi = cfg.gripper_force_range
    where = lo + (hi - lo) * torch.rand(cfg.num_grippers, generator=generator, dtype=torch.float64)
    force = flo + (fhi - flo) * torch.rand(cfg.num_grippers, generator=generator, dtype=torch.float64)
    return where, force


def _gripper_layout(
    cfg: StampFormingConfig, x0: Tensor, per_ply: int, where: Tensor
) -> tuple[Tensor, Tensor]:
    """Gripped node of every ply ``[G, P]`` and space-fixed anchors ``[G, 3]`` for one process."""
    lx, ly = cfg.ply_size
    nodes, anchors = [], []
    for g in range(cfg.num_grippers):
        point = [lx, float(where[g]) * ly, 0.0] if g == 0 else [float(where[g]) * lx, ly, 0.0]
        base = int(((x0[:per_ply] - torch.tensor(point, dtype=x0.dtype)) ** 2).sum(1).argmin())
        nodes.append(base + per_ply * torch.arange(cfg.num_plies))
        outward = torch.tensor([1.0, 0.0, 0.0] if g == 0 else [0.0, 1.0, 0.0], dtype=x0.dtype)
        anchors.append(x0[base] + cfg.gripper_anchor_distance * outward)
    if not nodes:
        return torch.empty(0, cfg.num_plies, dtype=torch.long), torch.empty(0, 3, dtype=x0.dtype)
    return torch.stack(nodes), torch.stack(anchors)


def _clamp_patch(x0: Tensor, per_ply: int, centre: int, radius: float) -> Tensor:
    """Nodes of ``centre``'s ply within ``radius`` of it in the flat start ``x0`` (``centre`` first)."""
    if radius <= 0:
        return torch.tensor([centre])
    first = centre // per_ply * per_ply
    ply = x0[first : first + per_ply]
    near = torch.nonzero((ply - x0[centre]).norm(dim=1) <= radius).squeeze(1) + first
    return torch.cat([torch.tensor([centre]), near[near != centre]])


class ForceParts(NamedTuple):
    """The forces on the ply nodes by kind, ``[Bn, 3]`` each; their sum is the total force."""

    elastic: Tensor  # membrane and bending
    viscous: Tensor  # matrix and bending viscosity
    die: Tensor  # normal (penalty) contact
    die_friction: Tensor
    punch: Tensor
    punch_friction: Tensor
    ply: Tensor  # ply on ply, normal
    ply_friction: Tensor
    grippers: Tensor
    contact_damping: Tensor  # of the die and ply-on-ply contacts
    punch_damping: Tensor


class LaminateModel:
    """Ply mechanics of ``B`` process settings as one disjoint system of ``B * n`` ply nodes.

    Args:
        cfg: Settings.
        mesh: The single-copy mesh from :func:`build_mesh` (plies first).
        processes: ``(where [G], force [G])`` per copy, from :func:`sample_process`.
    """

    def __init__(
        self, cfg: StampFormingConfig, mesh: MultiComponentMesh, processes: Sequence[tuple[Tensor, Tensor]]
    ) -> None:
        self.cfg = cfg
        self.copies = len(processes)
        n = int((mesh.node_type == NodeType.PLY).sum())  # plies come first in the mesh
        self.n, self.per_ply = n, n // cfg.num_plies
        x0 = mesh.pos[:n]
        tris = torch.cat([mesh.cells[k] for k in range(cfg.num_plies)])
        layer = mesh.component[:n]  # ply index 0 (bottom) .. P-1 (top)
        angles = torch.tensor([math.radians(a) for a in cfg.ply_angles], dtype=torch.float64)

        # B disjoint copies
        offsets = torch.arange(self.copies) * n
        self.x0 = x0.repeat(self.copies, 1)  # [Bn, 3]
        self.tris = (tris[None] + offsets[:, None, None]).reshape(-1, 3)
        self.layer = layer.repeat(self.copies)
        self.membrane = OrthotropicMembrane(
            self.x0[:, :2],
            self.tris,
            angles.repeat_interleave(mesh.cells[0].size(0)).repeat(self.copies),
            cfg.fiber_stiffness,
            cfg.transverse_stiffness,
            cfg.shear_stiffness,
            cfg.compression_ratio,
            cfg.matrix_viscosity,
        )
        lx, ly = cfg.ply_size
        tol = 1e-9 * max(lx, ly)
        on_x0, on_y0 = self.x0[:, 0].abs() < tol, self.x0[:, 1].abs() < tol
        on_x1, on_y1 = (self.x0[:, 0] - lx).abs() < tol, (self.x0[:, 1] - ly).abs() < tol
        self.bending = QuadraticBending(
            self.x0[:, :2],
            self.tris,
            ~(on_x0 | on_y0 | on_x1 | on_y1),
            cfg.bending_stiffness,
            cfg.bending_viscosity,
        )
        # Symmetry planes e1 = 0 and e2 = 0: u1 = 0 resp. u2 = 0 (x0 is 0 there, so x * free).
        self.free = torch.ones_like(self.x0)
        self.free[on_x0, 0] = 0.0
        self.free[on_y0, 1] = 0.0

        # Tool contact through the stack: ply k keeps k plies' thickness from the die and
        # P-1-k from the punch; friction acts on the outer plies, which touch the tools.
        h, k = cfg.ply_thickness, self.layer.double()
        self.die_offset = k * h
        self.punch_offset = (cfg.num_plies - 1 - k) * h
        self.die_friction = (self.layer == 0).double()
        self.punch_friction = (self.layer == cfg.num_plies - 1).double()

        # Grippers: a needle through all plies (or a clamp: the nodes of each ply within
        # gripper_clamp_radius) pulling towards a space-fixed anchor.
        layouts = [_gripper_layout(cfg, x0, self.per_ply, where) for where, _ in processes]
        self.gripper_nodes = [nodes for nodes, _ in layouts]  # per copy, local indices [G, P]
        self.anchors = [a for _, a in layouts]
        index, anchor, pull = [], [], []
        for (nodes, anchors), (_, force), o in zip(layouts, processes, offsets, strict=True):
            for g in range(nodes.size(0)):
                for centre in nodes[g].tolist():  # one gripped node per ply
                    patch = _clamp_patch(x0, self.per_ply, centre, cfg.gripper_clamp_radius)
                    index.append(patch + o)
                    anchor.append(anchors[g] + (x0[patch] - x0[centre]))  # a rigid clamp
                    share = float(force[g]) / (cfg.num_plies * patch.numel())  # N per clamped node
                    pull.append(torch.full((patch.numel(),), share, dtype=x0.dtype))
        empty = torch.empty(0, dtype=torch.long)
        self.gripper_index = torch.cat(index) if index else empty  # [K]: every clamped node
        self.gripper_anchor = torch.cat(anchor) if anchor else torch.empty(0, 3, dtype=x0.dtype)  # [K, 3]
        self.gripper_pull = torch.cat(pull) if pull else torch.empty(0, dtype=x0.dtype)  # [K]

        # Ply-on-ply contact: every node of ply k >= 1 against a nearby node of ply k - 1.
        self.pairs_upper = torch.nonzero(self.layer > 0).squeeze(1)
        # ply_contact "face": the triangles around a node are the candidate faces of its partners
        self.node_faces = incident_faces(self.tris, self.x0.size(0))  # [Bn, D]
        self.pairs_lower = torch.zeros_like(self.pairs_upper)

        # Lumped masses, and the explicit time step from the stability limit.
        node_area = torch.zeros(self.x0.size(0), dtype=torch.float64)
        for i in range(3):
            node_area.index_add_(0, self.tris[:, i], self.membrane.area / 3.0)
        self.mass = (cfg.areal_mass * node_area)[:, None]  # [Bn, 1]
        if cfg.selective_mass_scaling:
            # the light edge and corner nodes get the mass that the median node's limit needs
            stiffness = self.stiffness_bound()
            target = (stiffness / self.mass[:, 0]).median()  # omega^2
            self.mass = torch.maximum(self.mass, (stiffness / target)[:, None])
        frame = cfg.duration / cfg.num_steps
        critical = self.critical_time_step()
        if cfg.substeps is None:
            self.substeps = max(1, math.ceil(frame / (cfg.time_step_safety * critical)))
        else:
            self.substeps = cfg.substeps
            if frame / self.substeps > critical:
                raise ValueError(
                    f"StampFormingConfig: substeps={cfg.substeps} is unstable (time step "
                    f"{frame / cfg.substeps:.3g} s > critical {critical:.3g} s); "
                    f"use at least {math.ceil(frame / critical)} or None"
                )
        self.dt = frame / self.substeps
        # Friction may at most stop a node within one step; a node can have several friction
        # sources (a tool and ply-on-ply pairs), so each gets a share of m / dt.
        self.friction_cap = 0.25 * self.mass / self.dt  # [Bn, 1]
        # contact damping: a fraction of the critical damping of the penalty spring on the node
        self.contact_damping_coeff = (
            2.0 * cfg.contact_damping * (cfg.contact_stiffness * self.mass).sqrt()
        )  # [Bn, 1]
        self.pair_friction_cap = torch.zeros_like(self.pairs_upper, dtype=torch.float64)[:, None]

    def to(self, device: torch.device | str) -> LaminateModel:
        """Move the solver's tensors (this model's, the membrane's and the bending's) to ``device``.

        The per-copy gripper layouts (``gripper_nodes``, ``anchors``) stay on the CPU: they
        describe the trajectories, the solver uses ``gripper_index`` and ``gripper_anchor``.
        """
        for part in (self, self.membrane, self.bending):
            for name, value in vars(part).items():
                if isinstance(value, Tensor):
                    setattr(part, name, value.to(device))
        return self

    def _membrane_bound(self, modulus: float) -> Tensor:
        """Per-node Gershgorin-style bound ``[Bn]`` of a membrane operator of ``modulus`` (N/mm, N s/mm)."""
        tris, x0 = self.tris, self.x0
        edge2 = torch.stack([(x0[tris[:, i]] - x0[tris[:, (i + 1) % 3]]).pow(2).sum(1) for i in range(3)])
        per_tri = 2.0 * modulus * self.membrane.area / edge2.min(0).values
        out = torch.zeros(x0.size(0), dtype=x0.dtype)
        for i in range(3):
            out.index_add_(0, tris[:, i], per_tri)
        return out

    def stiffness_bound(self) -> Tensor:
        """A per-node upper bound of the stiffness (N/mm), for the mass scaling, ``[Bn]``."""
        cfg = self.cfg
        stiff = self._membrane_bound(cfg.fiber_stiffness + cfg.transverse_stiffness + cfg.shear_stiffness)
        # contact: both tools, one ply-on-ply pair as the upper node and a few as the lower one
        return stiff + 6.0 * cfg.contact_stiffness + self.bending.stiffness_bound()

    def viscosity_bound(self) -> Tensor:
        """A per-node upper bound of the explicit viscous coefficient (N s/mm), ``[Bn]``."""
        cfg = self.cfg
        contact = 2.0 * cfg.contact_damping * (cfg.contact_stiffness * self.mass[:, 0]).sqrt()
        return (
            self._membrane_bound(2.0 * cfg.matrix_viscosity)
            + self.bending.rate_ratio * self.bending.stiffness_bound()
            + 6.0 * contact  # as many contacts as the stiffness bound counts
        )

    def critical_time_step(self) -> float:
        """The explicit stability limit (s): ``min_i 2 / w_i (sqrt(1 + z_i^2) - z_i)``.

        ``w_i = sqrt(k_i / m_i)`` from :meth:`stiffness_bound` and the damping ratio
        ``z_i = c_i / (2 m_i w_i)`` of the explicit viscous forces (:meth:`viscosity_bound`); the
        mass-proportional damping is integrated implicitly and does not limit the step.
        """
        m = self.mass[:, 0]
        omega = (self.stiffness_bound() / m).sqrt()
        zeta = self.viscosity_bound() / (2.0 * m * omega)
        return float((2.0 / omega * ((1.0 + zeta * zeta).sqrt() - zeta)).min())

    def refresh_pairs(self, x: Tensor) -> None:
        """Choose every ply-on-ply partner for the next saved step (``pairs_lower``, ``[M]``).

        The partner of a node of ply k >= 1 is the nearest node of ply k - 1 of the same copy
        (``ply_contact = "node"``), or the triangle around that node whose closest point is
        nearest (``"face"``).
        """
        lower = []
        for b in range(self.copies):
            for k in range(1, self.cfg.num_plies):
                start = b * self.n + k * self.per_ply
                up, low = x[start : start + self.per_ply], x[start - self.per_ply : start]
                lower.append(nearest_nodes(up, low) + start - self.per_ply)
        nearest = torch.cat(lower)
        # a pair's friction may stop the relative motion of the lighter node within one step
        self.pair_friction_cap = torch.minimum(self.mass[self.pairs_upper], self.mass[nearest]) / self.dt
        if self.cfg.ply_contact == "face":
            candidates = self.node_faces[nearest]  # [M, D]
            *_, best = ply_on_face_gap(x, self.pairs_upper, candidates, self.tris, self.cfg.ply_thickness)
            self.pairs_lower = candidates.gather(1, best[:, None]).squeeze(1)
        else:
            self.pairs_lower = nearest

    def force_parts(
        self, x: Tensor, v: Tensor, travel: Tensor, punch_speed: float, pairs_lower: Tensor, pair_cap: Tensor
    ) -> ForceParts:
        """Every force on every ply node, ``[Bn, 3]`` each (``travel``: punch travel, 0-dim tensor)."""
        cfg = self.cfg
        zero = torch.zeros_like(x)
        membrane, viscous = self.membrane.forces_and_viscous(x, v)
        elastic = membrane + self.bending.forces(x)
        if cfg.bending_viscosity > 0:
            viscous = viscous + self.bending.viscous_forces(v)
        xy = x[:, :2]
        die_z, die_grad = die_surface(xy, cfg)
        damped = cfg.contact_damping > 0
        die, f_n, normal = height_field_contact(
            x, die_z, die_grad, 1.0, self.die_offset, cfg.contact_stiffness
        )
        die_friction = smooth_friction(
            f_n * self.die_friction, v, normal, cfg.friction_tool, self.friction_cap
        )
        damping = contact_damping(f_n, v, normal, self.contact_damping_coeff) if damped else zero
        punch_z, punch_grad = punch_surface(xy, travel, cfg)
        punch, f_n, normal = height_field_contact(
            x, punch_z, punch_grad, -1.0, self.punch_offset, cfg.contact_stiffness
        )
        v_rel = v + torch.tensor([0.0, 0.0, punch_speed], dtype=v.dtype, device=v.device)  # punch along -e3
        punch_friction = smooth_friction(
            f_n * self.punch_friction, v_rel, normal, cfg.friction_tool, self.friction_cap
        )
        punch_damping = contact_damping(f_n, v_rel, normal, self.contact_damping_coeff) if damped else zero
        ply, ply_friction = zero, zero
        if cfg.num_plies > 1:
            # the pair's reduced mass (equal masses: half the lighter one's, pair_cap * dt)
            pair_damping = (
                2.0 * cfg.contact_damping * (0.5 * cfg.contact_stiffness * pair_cap * self.dt).sqrt()
            )
            if cfg.ply_contact == "face":
                ply, ply_friction, ply_damping = ply_on_face_contact(
                    x,
                    v,
                    self.pairs_upper,
                    pairs_lower,
                    self.tris,
                    cfg.ply_thickness,
                    cfg.contact_stiffness,
                    cfg.friction_ply,
                    pair_cap,
                    pair_damping if damped else None,
                )
            else:
                ply, ply_friction, ply_damping = ply_on_ply_contact(
                    x,
                    v,
                    self.pairs_upper,
                    pairs_lower,
                    vertex_normals(x, self.tris),
                    cfg.ply_thickness,
                    cfg.contact_stiffness,
                    cfg.friction_ply,
                    pair_cap,
                    pair_damping if damped else None,
                )
            damping = damping + ply_damping
        grippers = zero
        if cfg.num_grippers:
            d = self.gripper_anchor - x[self.gripper_index]  # [K, 3]
            pull = self.gripper_pull[:, None] * d / d.norm(dim=1, keepdim=True).clamp_min(1e-9)
            grippers = zero.index_add(0, self.gripper_index, pull)
        return ForceParts(
            elastic,
            viscous,
            die,
            die_friction,
            punch,
            punch_friction,
            ply,
            ply_friction,
            grippers,
            damping,
            punch_damping,
        )

    def per_copy(self, values: Tensor) -> Tensor:
        """Sums of per-node ``values`` ``[Bn]`` over each copy, ``[B]``."""
        return values.view(self.copies, -1).sum(1)

    def state_energies(self, x: Tensor, v: Tensor, travel: Tensor, pairs_lower: Tensor) -> Tensor:
        """Energies of the state (N mm) per copy ``[B, 4]``: kinetic, membrane, bending, contact.

        ``contact`` is the penalty energy ``f_n^2 / (2 k)`` of the tool and ply-on-ply contacts.
        """
        cfg = self.cfg
        k = cfg.contact_stiffness
        half_compliance = 0.5 / k if k > 0 else 0.0  # f_n^2 / (2 k); no contact without stiffness
        xy = x[:, :2]
        kinetic = self.per_copy(0.5 * self.mass[:, 0] * (v * v).sum(1))
        membrane = self.membrane.cell_energy(x).view(self.copies, -1).sum(1)
        bending = self.per_copy(self.bending.node_energy(x))
        die_z, die_grad = die_surface(xy, cfg)
        _, die_n, _ = height_field_contact(x, die_z, die_grad, 1.0, self.die_offset, k)
        punch_z, punch_grad = punch_surface(xy, travel, cfg)
        _, punch_n, _ = height_field_contact(x, punch_z, punch_grad, -1.0, self.punch_offset, k)
        contact = self.per_copy((die_n * die_n + punch_n * punch_n) * half_compliance)
        if cfg.num_plies > 1 and self.pairs_upper.numel():
            if cfg.ply_contact == "face":
                height, *_ = face_plane(x, self.pairs_upper, pairs_lower, self.tris)
                _, ply_energy = faded_penalty(cfg.ply_thickness - height, cfg.ply_thickness, k)
            else:
                normals = vertex_normals(x, self.tris)
                ply_n, _ = ply_on_ply_normal(x, self.pairs_upper, pairs_lower, normals, cfg.ply_thickness, k)
                ply_energy = ply_n * ply_n * half_compliance
            contact = contact + ply_energy.view(self.copies, -1).sum(1)
        return torch.stack([kinetic, membrane, bending, contact], 1)

    def step_function(
        self, compile: bool = False
    ) -> Callable[[Tensor, Tensor, Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
        """One explicit sub-step ``(x, v, travel, pairs_lower, pair_cap) -> (x, v, work)``.

        Semi-implicit Euler with implicit mass-proportional damping:
        ``v' = (v + dt f / m) / (1 + c dt)``, ``x' = x + dt v'``; symmetry constraints zero the
        constrained velocity components of nodes on the planes, and no node may cross them.
        ``work`` ``[B, 6]`` is what the sub-step added to the path terms of the energy balance
        (:data:`torch_ampn.sim.energy.WORK_TERMS`, N mm) per copy: each force's power on the
        sub-step's mean velocity ``(v + v') / 2`` times ``dt`` (the punch's on the punch's velocity;
        friction's and the contact damping's on the relative velocity).
        """
        inv_mass_dt = self.dt / self.mass  # [Bn, 1]
        damp_free = self.free / (1.0 + self.cfg.damping * self.dt)  # [Bn, 3]
        mass_damping = self.cfg.damping * self.mass[:, 0]  # [Bn] N s/mm
        half_mass = 0.5 * self.mass[:, 0]
        speed, dt = self.cfg.stroke / self.cfg.duration, self.dt
        punch_velocity = torch.tensor([0.0, 0.0, -speed], dtype=self.x0.dtype, device=self.x0.device)
        lower = torch.tensor([0.0, 0.0, -math.inf], dtype=self.x0.dtype, device=self.x0.device)  # x1, x2 >= 0

        def step(
            x: Tensor, v: Tensor, travel: Tensor, pairs_lower: Tensor, pair_cap: Tensor
        ) -> tuple[Tensor, Tensor, Tensor]:
            parts = self.force_parts(x, v, travel, speed, pairs_lower, pair_cap)
            v_new = (v + sum(parts) * inv_mass_dt) * damp_free
            x_new = x + dt * v_new
            # the symmetry planes are walls for the rest of the quarter model, too
            blocked = x_new < lower
            v_out = torch.where(blocked, torch.zeros_like(v_new), v_new)
            # powers on the mean velocity of the sub-step: m (v' - v) / dt = f makes
            # 0.5 m (|v'|^2 - |v|^2) = dt f . (v + v') / 2 exact for the kinetic energy
            v_mean = 0.5 * (v + v_new)
            punch = parts.punch + parts.punch_friction + parts.punch_damping
            power = torch.stack(
                [
                    mass_damping * (v_new * v_mean).sum(1)
                    - (parts.contact_damping * v_mean + parts.punch_damping * (v_mean - punch_velocity)).sum(
                        1
                    ),
                    -(parts.viscous * v_mean).sum(1),
                    -(
                        (parts.die_friction + parts.ply_friction) * v_mean
                        + parts.punch_friction * (v_mean - punch_velocity)
                    ).sum(1),
                    half_mass * (v_new * v_new - v_out * v_out).sum(1) / dt,
                    (parts.grippers * v_mean).sum(1),
                    (punch * punch_velocity).sum(1),
                ],
                1,
            )  # [Bn, 6]
            work = dt * power.view(self.copies, -1, power.size(1)).sum(1)  # [B, 6]
            return torch.maximum(x_new, lower), v_out, work

        # a code object per mesh and part: the step reads the tool geometry as constants, so each
        # part of a family compiles its own step, rather than recompiling a shared one until the
        # 9th part of a process runs eagerly; calls for the same part reuse it (torch_ampn.utils.own_code)
        part = (tuple(self.x0.shape), str(self.x0.device), self.x0.dtype, repr(self.cfg))
        return torch.compile(own_code(step, key=part), dynamic=False) if compile else step


def _tool_motion(cfg: StampFormingConfig, mesh: MultiComponentMesh, n: int) -> tuple[Tensor, Tensor]:
    """Saved times ``[T+1]`` and tool positions ``[T+1, N - n, 3]``: the punch moves, the die stays."""
    punch = mesh.component == cfg.num_plies
    punch_xy = mesh.pos[punch, :2]
    times = torch.linspace(0.0, cfg.duration, cfg.num_steps + 1, dtype=torch.float64)
    tool_frames = mesh.pos[n:].expand(cfg.num_steps + 1, -1, -1).clone()
    for i, t in enumerate(times):
        tool_frames[i, punch[n:], 2] = punch_surface(punch_xy, float(punch_travel(float(t), cfg)), cfg)[0]
    return times, tool_frames


def _fiber_directions(cfg: StampFormingConfig, mesh: MultiComponentMesh, n: int) -> Tensor:
    """Unit fibre direction of every node ``[N, 3]`` (zero on the tools)."""
    fiber = torch.zeros(mesh.num_nodes, 3, dtype=torch.float64)
    angle = torch.tensor(
        [math.radians(cfg.ply_angles[c]) for c in mesh.component[:n].tolist()], dtype=torch.float64
    )
    fiber[:n, 0], fiber[:n, 1] = torch.cos(angle), torch.sin(angle)
    return fiber


def _trajectory(
    mesh: MultiComponentMesh,
    plies: Tensor,
    times: Tensor,
    tool_frames: Tensor,
    fiber: Tensor,
    gripper_nodes: Tensor,
    gripper_anchor: Tensor,
    gripper_force: Tensor,
    **meta: Any,
) -> Trajectory:
    """The float32 trajectory of ply positions ``plies`` ``[T+1, n, 3]`` and tool positions ``tool_frames``.

    ``meta`` follows ``simulator="torch_ampn.sim"`` in the trajectory's ``meta``, in the given order.
    """
    return Trajectory(
        pos=torch.cat([plies, tool_frames], 1).float(),
        time=times.float(),
        cells=[c.clone() for c in mesh.cells],
        component=mesh.component.clone(),
        node_type=mesh.node_type.clone(),
        fiber=fiber.float(),
        names=list(mesh.names),
        gripper_nodes=gripper_nodes,
        gripper_anchor=gripper_anchor.float(),
        gripper_force=gripper_force.float(),
        meta=dict(simulator="torch_ampn.sim", **meta),
    )


def explicit_process(
    cfg: StampFormingConfig,
    gripper_positions: Sequence[float] | Tensor,
    gripper_forces: Sequence[float] | Tensor,
) -> tuple[Tensor, Tensor]:
    """Checked ``(positions [G], forces [G])`` (float64) of one process setting of ``cfg``.

    Positions are fractions of each gripper's free edge in ``[0, 1]``, forces in N (``>= 0``).
    """
    where = torch.as_tensor(gripper_positions, dtype=torch.float64).reshape(-1)
    force = torch.as_tensor(gripper_forces, dtype=torch.float64).reshape(-1)
    for name, value in (("gripper_positions", where), ("gripper_forces", force)):
        if value.numel() != cfg.num_grippers:
            raise ValueError(f"{name} needs {cfg.num_grippers} values, got {value.numel()}")
        if not torch.isfinite(value).all():
            raise ValueError(f"{name} must be finite, got {value.tolist()}")
    if ((where < 0) | (where > 1)).any():
        raise ValueError(f"gripper_positions are fractions of the edge in [0, 1], got {where.tolist()}")
    if (force < 0).any():
        raise ValueError(f"gripper_forces must be >= 0 N, got {force.tolist()}")
    return where, force


def process_trajectory(
    config: StampFormingConfig | None = None,
    gripper_positions: Sequence[float] | Tensor | None = None,
    gripper_forces: Sequence[float] | Tensor | None = None,
    seed: int | None = None,
) -> Trajectory:
    """A trajectory of a process setting *without* solving it: tools on their prescribed path, plies at rest.

    This is the input of a surrogate rollout for new process settings (``torch-ampn predict``):
    the initial state, the mesh, the gripper layout and the tool motion are exact; the ply
    positions after step 0 are placeholders (equal to the initial state), and
    ``meta["ground_truth"]`` is ``False``.

    Args:
        config: Simulator settings (default: the coarse default).
        gripper_positions: Position of each gripper along its free edge as a fraction in
            ``[0, 1]``, ``[G]``.
        gripper_forces: Pulling force of each gripper in N, ``[G]``.
        seed: Instead of explicit settings, sample them as :func:`simulate` does for ``seed``.
    """
    cfg = config or StampFormingConfig()
    cfg.validate()
    if seed is not None:
        if gripper_positions is not None or gripper_forces is not None:
            raise ValueError("give either a seed or explicit gripper positions and forces, not both")
        where, force = sample_process(cfg, seed)
    else:
        if gripper_positions is None or gripper_forces is None:
            raise ValueError("process_trajectory needs gripper_positions and gripper_forces (or a seed)")
        where, force = explicit_process(cfg, gripper_positions, gripper_forces)
    return _unsolved(cfg, [(where, force)], [{} if seed is None else {"seed": int(seed)}])[0]


def process_trajectories(
    config: StampFormingConfig | None,
    settings: Sequence[tuple[Sequence[float] | Tensor, Sequence[float] | Tensor]],
) -> list[Trajectory]:
    """:func:`process_trajectory` of many settings of one process, its mesh and tool motion built once.

    Args:
        config: Simulator settings (default: the coarse default).
        settings: ``(gripper_positions [G], gripper_forces [G])`` per trajectory.
    """
    cfg = config or StampFormingConfig()
    cfg.validate()
    processes = [explicit_process(cfg, where, force) for where, force in settings]
    return _unsolved(cfg, processes, [{} for _ in processes])


def _unsolved(
    cfg: StampFormingConfig, processes: Sequence[tuple[Tensor, Tensor]], metas: Sequence[dict]
) -> list[Trajectory]:
    """The unsolved trajectories (plies at rest, tools on their path) of checked ``processes``."""
    mesh = build_mesh(cfg)
    n = int((mesh.node_type == NodeType.PLY).sum())
    times, tool_frames = _tool_motion(cfg, mesh, n)
    plies = mesh.pos[:n].expand(cfg.num_steps + 1, -1, -1)
    fiber = _fiber_directions(cfg, mesh, n)
    out = []
    for (where, force), meta in zip(processes, metas, strict=True):
        nodes, anchors = _gripper_layout(cfg, mesh.pos[:n], n // cfg.num_plies, where)
        out.append(
            _trajectory(
                mesh,
                plies,
                times,
                tool_frames,
                fiber,
                nodes,
                anchors,
                force,
                ground_truth=False,
                config=cfg.to_dict(),
                gripper_edge_fraction=where.tolist(),
                **meta,
            )  # fmt: skip
        )
    return out


def simulate_batch(
    config: StampFormingConfig | None = None,
    seeds: Sequence[int] = (0,),
    progress: bool = False,
    compile: bool = False,
    device: torch.device | str = "cpu",
    perturbation: float = 0.0,
    settings: Sequence[tuple[Sequence[float] | Tensor, Sequence[float] | Tensor]] | None = None,
) -> list[Trajectory]:
    """Simulate one process per seed, all at once, and return their trajectories.

    Gripper positions and forces are sampled from each seed (uniform along the free edges
    and in ``gripper_force_range``) unless ``settings`` gives them. Eager, the same config and
    seed give the same trajectory whatever the batch it is simulated in; with ``compile`` the
    last bits depend on the batch, and the chaotic forming amplifies them (see
    ``docs/simulator.md``).

    Args:
        config: Settings; the coarse default when ``None``.
        seeds: One seed per trajectory.
        progress: Show a progress bar over the saved steps.
        compile: Run the sub-step through ``torch.compile`` (costs a few seconds once per
            process; several times faster afterwards).
        device: Where the solver runs (e.g. ``"cuda"``: worth it for many trajectories at
            once or fine meshes); the set-up and the returned trajectories are on the CPU.
            Another device gives other last bits, which the forming amplifies.
        perturbation: Move every free coordinate of the initial ply nodes by a uniform random
            amount in ``[-perturbation, perturbation]`` mm (drawn from the seed; 0: none): the
            same settings from an imperceptibly different start, to measure how chaotic the
            forming is (:mod:`torch_ampn.sim.spread`). Recorded in ``meta["initial_perturbation"]``.
        settings: Explicit ``(gripper_positions [G], gripper_forces [G])`` per trajectory
            (edge fractions, N), e.g. the settings a design study chose; ``seeds`` then only
            name the trajectories (default ``0 .. len(settings) - 1``).

    Returns:
        One :class:`~torch_ampn.data.Trajectory` per seed, each with ``num_steps + 1``
        saved states of plies, punch and die (float32, CPU).
    """
    cfg = config or StampFormingConfig()
    cfg.validate()
    if settings is not None:
        settings = list(settings)
        seeds = range(len(settings)) if tuple(seeds) == (0,) else seeds
        if len(seeds) != len(settings):
            raise ValueError(f"got {len(seeds)} seeds for {len(settings)} settings")
    if len(seeds) == 0:
        raise ValueError("simulate_batch needs at least one seed")
    if settings is None:
        processes = [sample_process(cfg, int(s)) for s in seeds]
    else:
        processes = [explicit_process(cfg, where, force) for where, force in settings]
    mesh = build_mesh(cfg)
    # spinning threads, as many as other processes leave cores
    with follow_free_cpu(device) as threads:
        model = LaminateModel(cfg, mesh, processes).to(device)
        step = model.step_function(compile)
        n, copies = model.n, model.copies
        x, v = model.x0.clone(), torch.zeros_like(model.x0)
        if perturbation < 0:
            raise ValueError(f"perturbation must be >= 0 mm, got {perturbation}")
        if perturbation > 0:
            for b, seed in enumerate(seeds):
                g = torch.Generator().manual_seed(int(seed))
                noise = (2 * torch.rand(n, 3, generator=g, dtype=x.dtype) - 1) * perturbation  # [n, 3]
                x[b * n : (b + 1) * n] += noise.to(x.device) * model.free[b * n : (b + 1) * n]
        frames = [x.clone()]
        zero_travel = torch.zeros((), dtype=x.dtype, device=x.device)
        work = torch.zeros(copies, len(WORK_TERMS), dtype=x.dtype, device=x.device)  # [B, 6] N mm
        states = [model.state_energies(x, v, zero_travel, model.pairs_lower)]  # [B, 4] per saved step
        works = [work.clone()]
        steps = range(1, cfg.num_steps + 1)
        if progress:
            from tqdm.auto import tqdm

            steps = tqdm(steps, desc=f"simulate x{copies}", unit="step", leave=False)
        for k in steps:
            threads.step()
            model.refresh_pairs(x)
            for sub in range(model.substeps):
                t = ((k - 1) * model.substeps + sub + 1) * model.dt
                travel = torch.tensor(float(punch_travel(t, cfg)), dtype=x.dtype, device=x.device)
                # the first call compiles: its kernels are built for every thread torch may use
                with threads.at_ceiling() if compile and k == 1 and sub == 0 else nullcontext():
                    x, v, dw = step(x, v, travel, model.pairs_lower, model.pair_friction_cap)
                work = work + dw
            if not torch.isfinite(x).all():
                raise FloatingPointError(f"simulation diverged at step {k} (seeds {list(seeds)})")
            frames.append(x.clone())
            states.append(model.state_energies(x, v, travel, model.pairs_lower))
            works.append(work.clone())
        ply_frames = torch.stack(frames).cpu().view(cfg.num_steps + 1, copies, n, 3)
        energies = torch.cat([torch.stack(states), torch.stack(works)], 2).cpu()  # [T+1, B, 10]

    times, tool_frames = _tool_motion(cfg, mesh, n)
    fiber = _fiber_directions(cfg, mesh, n)
    out = []
    for b, seed in enumerate(seeds):
        where, force = processes[b]
        out.append(
            _trajectory(
                mesh,
                ply_frames[:, b],
                times,
                tool_frames,
                fiber,
                model.gripper_nodes[b],
                model.anchors[b],
                force,
                seed=int(seed),
                config=cfg.to_dict(),
                substeps=model.substeps,
                gripper_edge_fraction=where.tolist(),
                energy=energy_record(energies[:, b]),
                **({"initial_perturbation": float(perturbation)} if perturbation else {}),
            )
        )
    return out


def simulate(
    config: StampFormingConfig | None = None,
    seed: int = 0,
    progress: bool = False,
    compile: bool = False,
    device: torch.device | str = "cpu",
) -> Trajectory:
    """Simulate one stamp-forming process (see :func:`simulate_batch`)."""
    return simulate_batch(config, [seed], progress=progress, compile=compile, device=device)[0]
