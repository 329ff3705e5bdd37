"""Ply mechanics: orthotropic membrane (St. Venant-Kirchhoff on triangles) and bending."""

from __future__ import annotations

import torch
from torch import Tensor


class OrthotropicMembrane:
    r"""Membrane forces of triangles with a fibre direction, stiff along the fibre, soft in shear.

    Per triangle, with the Green strain :math:`E = \tfrac12 (F^\top F - I)` expressed in the
    fibre frame :math:`(a, b)` of the reference configuration, the energy is

    .. math::
        W = A_0 \left[\tfrac12 C_f(E_{aa}) E_{aa}^2 + \tfrac12 C_t E_{bb}^2 + C_s E_{ab}^2\right],

    where :math:`C_f` drops to ``compression_ratio * C_f`` under fibre compression (thin plies
    buckle instead of carrying compression), which lets wrinkles form.

    Args:
        ref_xy: Reference (flat) coordinates of the nodes, ``[N, 2]``.
        triangles: ``[F, 3]`` node indices (counter-clockwise).
        fiber_angle: Fibre angle of every triangle in radians, ``[F]``.
        fiber, transverse, shear: Stiffnesses :math:`C_f, C_t, C_s` in N/mm.
        compression_ratio: Fibre stiffness factor under compression.
        viscosity: Matrix viscosity :math:`\eta` in N s/mm (viscosity times ply thickness): a
            Kelvin-Voigt stress :math:`\eta \dot E` on the transverse and shear strain rates,
            with the dissipation potential :math:`A_0 \eta (\tfrac12 \dot E_{bb}^2 + \dot E_{ab}^2)`
            (:meth:`viscous_forces`). It resists deformation of the matrix, never rigid motion.
    """

    def __init__(
        self,
        ref_xy: Tensor,
        triangles: Tensor,
        fiber_angle: Tensor,
        fiber: float,
        transverse: float,
        shear: float,
        compression_ratio: float,
        viscosity: float = 0.0,
    ) -> None:
        self.viscosity = viscosity
        self.tri = triangles
        self.tri_flat = triangles.t().reshape(-1)  # [3F]: all first corners, then second, third
        x0, x1, x2 = (ref_xy[triangles[:, i]] for i in range(3))
        dm = torch.stack([x1 - x0, x2 - x0], 2)  # [F, 2, 2], columns are edges
        self.area = 0.5 * torch.linalg.det(dm).abs()  # [F]
        bm = torch.linalg.inv(dm)  # [F, 2, 2]
        a = torch.stack([torch.cos(fiber_angle), torch.sin(fiber_angle)], 1)  # [F, 2]
        b = torch.stack([-torch.sin(fiber_angle), torch.cos(fiber_angle)], 1)
        # F a = alpha_0 (x1 - x0) + alpha_1 (x2 - x0) with alpha = Bm a; likewise beta = Bm b.
        alpha, beta = (bm @ a[:, :, None]).squeeze(2), (bm @ b[:, :, None]).squeeze(2)  # [F, 2]
        self.alpha = alpha.t()[:, :, None]  # [2, F, 1]
        self.beta = beta.t()[:, :, None]
        self.c = (fiber, transverse, shear, compression_ratio)
        self.num_nodes = ref_xy.size(0)

    def strains(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Fibre-frame vectors ``F a``, ``F b`` ``[F, 3]`` and Green strains ``E_aa, E_bb, E_ab`` ``[F]``."""
        x0 = x[self.tri[:, 0]]
        e1, e2 = x[self.tri[:, 1]] - x0, x[self.tri[:, 2]] - x0
        fa = self.alpha[0] * e1 + self.alpha[1] * e2
        fb = self.beta[0] * e1 + self.beta[1] * e2
        e_aa = 0.5 * ((fa * fa).sum(1) - 1.0)
        e_bb = 0.5 * ((fb * fb).sum(1) - 1.0)
        e_ab = 0.5 * (fa * fb).sum(1)
        return fa, fb, e_aa, e_bb, e_ab

    def _corner_forces(self, fa: Tensor, fb: Tensor, s_aa: Tensor, s_bb: Tensor, s_ab: Tensor) -> Tensor:
        """Nodal forces ``[N, 3]`` of fibre-frame stresses ``s_aa, s_bb, s_ab`` ``[F]`` (``-dW/dx``)."""
        p = (self.area * s_aa)[:, None] * fa + (self.area * s_ab)[:, None] * fb
        q = (self.area * s_bb)[:, None] * fb + (self.area * s_ab)[:, None] * fa
        f1 = -(p * self.alpha[0] + q * self.beta[0])
        f2 = -(p * self.alpha[1] + q * self.beta[1])
        per_corner = torch.cat([-f1 - f2, f1, f2])  # [3F, 3] in the order of tri_flat
        return fa.new_zeros(self.num_nodes, 3).index_add_(0, self.tri_flat, per_corner)

    def forces(self, x: Tensor) -> Tensor:
        """Nodal forces ``[N, 3]`` at positions ``x`` ``[N, 3]``.

        With the second Piola-Kirchhoff stress ``S`` and ``P = F S``, the forces on corners 1
        and 2 are the columns of ``-A_0 P B_m^T``, written out in the fibre frame.
        """
        cf, ct, cs, comp = self.c
        fa, fb, e_aa, e_bb, e_ab = self.strains(x)
        s_aa = torch.where(e_aa < 0, comp * cf, cf) * e_aa
        return self._corner_forces(fa, fb, s_aa, ct * e_bb, cs * e_ab)

    def strain_rates(
        self, x: Tensor, v: Tensor, frame: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``F a``, ``F b`` ``[F, 3]`` and the transverse and shear strain rates ``dE_bb, dE_ab`` ``[F]``.

        ``frame``: ``(F a, F b)`` at ``x`` if already at hand (:meth:`strains`).
        """
        fa, fb = self.strains(x)[:2] if frame is None else frame
        v0 = v[self.tri[:, 0]]
        w1, w2 = v[self.tri[:, 1]] - v0, v[self.tri[:, 2]] - v0
        dfa = self.alpha[0] * w1 + self.alpha[1] * w2
        dfb = self.beta[0] * w1 + self.beta[1] * w2
        return fa, fb, (fb * dfb).sum(1), 0.5 * ((fa * dfb).sum(1) + (fb * dfa).sum(1))

    def viscous_forces(self, x: Tensor, v: Tensor, frame: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Matrix-viscosity forces ``[N, 3]`` at positions ``x`` and velocities ``v`` ``[N, 3]``.

        ``-dD/dv`` of the dissipation potential ``D = A_0 eta (dE_bb^2 / 2 + dE_ab^2)``; their
        power ``f . v = -2 D`` is never positive. ``frame``: as in :meth:`strain_rates`.
        """
        fa, fb, r_bb, r_ab = self.strain_rates(x, v, frame)
        eta = self.viscosity
        return self._corner_forces(fa, fb, torch.zeros_like(r_bb), eta * r_bb, eta * r_ab)

    def forces_and_viscous(self, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`forces` and :meth:`viscous_forces` (zero without viscosity), the strains computed once."""
        cf, ct, cs, comp = self.c
        fa, fb, e_aa, e_bb, e_ab = self.strains(x)
        s_aa = torch.where(e_aa < 0, comp * cf, cf) * e_aa
        elastic = self._corner_forces(fa, fb, s_aa, ct * e_bb, cs * e_ab)
        if self.viscosity == 0:
            return elastic, torch.zeros_like(elastic)
        return elastic, self.viscous_forces(x, v, (fa, fb))

    def cell_energy(self, x: Tensor) -> Tensor:
        """Membrane energy of every triangle ``[F]`` (N mm)."""
        cf, ct, cs, comp = self.c
        _, _, e_aa, e_bb, e_ab = self.strains(x)
        c_aa = torch.where(e_aa < 0, comp * cf, cf)
        return self.area * (0.5 * c_aa * e_aa**2 + 0.5 * ct * e_bb**2 + cs * e_ab**2)

    def energy(self, x: Tensor) -> Tensor:
        """Total membrane energy (N mm), used by tests to check the forces."""
        return self.cell_energy(x).sum()


def cotan_weights(ref_xy: Tensor, triangles: Tensor, num_nodes: int) -> tuple[Tensor, Tensor, Tensor]:
    """Cotangent-Laplacian edge weights and lumped (barycentric) node areas of a flat mesh.

    Returns:
        ``(edge_index [2, E], weight [E], area [N])`` with both directions of every edge, so
        that ``(L x)_i = sum_j w_ij (x_j - x_i)`` is symmetric in ``i, j``.
    """
    rows, cols, vals = [], [], []
    p = [ref_xy[triangles[:, i]] for i in range(3)]
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        u, v = p[j] - p[i], p[k] - p[i]
        cross = (u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).abs().clamp_min(1e-12)
        w = 0.5 * (u * v).sum(1) / cross  # half the cotangent of the angle at corner i: edge (j, k)
        rows += [triangles[:, j], triangles[:, k]]
        cols += [triangles[:, k], triangles[:, j]]
        vals += [w, w]
    lap = torch.sparse_coo_tensor(
        torch.stack([torch.cat(rows), torch.cat(cols)]),
        torch.cat(vals),
        (num_nodes, num_nodes),
        check_invariants=False,
    ).coalesce()
    e1, e2 = p[1] - p[0], p[2] - p[0]
    tri_area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()
    area = torch.zeros(num_nodes, dtype=ref_xy.dtype)
    for i in range(3):
        area.index_add_(0, triangles[:, i], tri_area / 3.0)
    return lap.indices().clone(), lap.values().clone(), area


class QuadraticBending:
    r"""Isometric quadratic bending (Bergou et al. 2006) restricted to interior nodes.

    :math:`W = \tfrac{k}{2} \sum_{i \in \text{interior}} |(L x)_i|^2 / A_i`, with the cotangent
    Laplacian :math:`L` of the flat reference mesh. It vanishes on every rigid motion (and
    every affine map) of the flat sheet and measures squared mean curvature under bending;
    the forces :math:`-k L A^{-1} L x` are linear in :math:`x` (``L`` is symmetric).

    ``viscosity`` :math:`\eta_b` (N mm s) adds the bending-rate forces :math:`-\eta_b L A^{-1} L v`
    (:meth:`viscous_forces`): a damping of bending (stiffness-proportional), none of rigid motion.
    """

    def __init__(
        self, ref_xy: Tensor, triangles: Tensor, interior: Tensor, stiffness: float, viscosity: float = 0.0
    ) -> None:
        n = ref_xy.size(0)
        self.rate_ratio = viscosity / stiffness if stiffness > 0 else 0.0  # s: eta_b / k
        (self.row, self.col), self.weight, area = cotan_weights(ref_xy, triangles, n)
        self.weight_col = self.weight[:, None]  # [E, 1]
        self.degree = torch.zeros(n, dtype=ref_xy.dtype).index_add_(0, self.row, self.weight)[
            :, None
        ]  # [N, 1]
        self.scale = (torch.where(interior, 1.0 / area.clamp_min(1e-12), torch.zeros_like(area)) * stiffness)[
            :, None
        ]
        if viscosity > 0 and stiffness <= 0:
            raise ValueError("QuadraticBending: a bending viscosity needs a positive bending stiffness")

    def laplacian(self, x: Tensor) -> Tensor:
        """``L x`` ``[N, 3]`` for ``x`` ``[N, 3]``."""
        return torch.zeros_like(x).index_add_(0, self.row, self.weight_col * x[self.col]) - self.degree * x

    def forces(self, x: Tensor) -> Tensor:
        """Nodal forces ``[N, 3]``."""
        return -self.laplacian(self.scale * self.laplacian(x))

    def viscous_forces(self, v: Tensor) -> Tensor:
        """Bending-rate forces ``[N, 3]`` at velocities ``v`` ``[N, 3]`` (power ``f . v <= 0``)."""
        return self.rate_ratio * self.forces(v)

    def node_energy(self, x: Tensor) -> Tensor:
        """Bending energy at every node ``[N]`` (N mm)."""
        lx = self.laplacian(x)
        return 0.5 * (self.scale * lx * lx).sum(1)

    def energy(self, x: Tensor) -> Tensor:
        """Total bending energy."""
        return self.node_energy(x).sum()

    def stiffness_bound(self) -> Tensor:
        """Gershgorin bound per node of the bending stiffness ``L S L``, ``[N]``."""
        s = self.scale[:, 0]
        abs_row = torch.zeros_like(s).index_add_(0, self.row, self.weight.abs()) + self.degree[:, 0].abs()
        contrib = torch.zeros_like(s).index_add_(
            0, self.row, self.weight.abs() * s[self.col] * abs_row[self.col]
        )
        return contrib + self.degree[:, 0] * s * abs_row
