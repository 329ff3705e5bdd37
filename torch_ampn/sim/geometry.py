"""Analytic quarter tool surfaces (height fields: double domes, domes, rounded boxes) and their meshes."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torch_ampn.sim.config import StampFormingConfig


def _bump(rho: Tensor, flat: float) -> tuple[Tensor, Tensor]:
    """Flat-topped cosine bump ``b(rho)`` (1 for rho <= flat, 0 for rho >= 1) and ``db/drho``."""
    s = ((rho - flat) / (1.0 - flat)).clamp(0.0, 1.0)
    b = 0.5 * (1.0 + torch.cos(math.pi * s))
    inside = (rho > flat) & (rho < 1.0)
    db = torch.where(inside, -0.5 * math.pi / (1.0 - flat) * torch.sin(math.pi * s), torch.zeros_like(rho))
    return b, db


def _footprint_radius(dx: Tensor, dy: Tensor, exponent: float) -> tuple[Tensor, Tensor, Tensor]:
    """Superellipse radius ``rho = (|dx|^p + |dy|^p)^(1/p)`` of scaled offsets and its gradient.

    Returns:
        ``(rho, drho/ddx, drho/ddy)``, each ``[N]``; ``p >= 2`` keeps the gradient continuous.
    """
    ux, uy = dx.abs(), dy.abs()
    rho = (ux.pow(exponent) + uy.pow(exponent)).pow(1.0 / exponent).clamp_min(1e-12)
    scale = rho.pow(1.0 - exponent)  # d rho / d|dx| = (|dx| / rho)^(p - 1)
    drho_dx = torch.sign(dx) * ux.pow(exponent - 1.0) * scale
    drho_dy = torch.sign(dy) * uy.pow(exponent - 1.0) * scale
    return rho, drho_dx, drho_dy


def dome_depth(xy: Tensor, cfg: StampFormingConfig, grow: float = 0.0) -> tuple[Tensor, Tensor]:
    """Depth ``D(x, y) >= 0`` of the double-dome cavity and its gradient.

    Two flat-topped domes centred at ``(+-dome_centre, 0)`` joined by a smooth union
    ``1 - (1 - b1)(1 - b2)``; the quarter model sees one dome and half of the saddle between
    them. A dome's footprint is an ellipse (``dome_exponent = 2``) or, for larger exponents, a
    superellipse: a rounded box. ``grow`` widens both semi-axes (the die cavity is wider than the
    punch).

    Args:
        xy: ``[N, 2]`` points in the e1-e2 plane.
        cfg: The simulator settings.
        grow: Extra semi-axis length, mm.

    Returns:
        ``(D [N], grad D [N, 2])``.
    """
    ax, ay = cfg.dome_axes[0] + grow, cfg.dome_axes[1] + grow
    out_b, out_g = [], []
    for cx in (cfg.dome_centre, -cfg.dome_centre):
        dx, dy = (xy[:, 0] - cx) / ax, xy[:, 1] / ay
        if cfg.dome_exponent == 2.0:  # the ellipse, in the form every dataset before boxes used
            rho = torch.sqrt(dx * dx + dy * dy).clamp_min(1e-12)
            b, db = _bump(rho, cfg.dome_flat_top)
            grad = torch.stack([db * dx / (rho * ax), db * dy / (rho * ay)], 1)
        else:
            rho, drho_dx, drho_dy = _footprint_radius(dx, dy, cfg.dome_exponent)
            b, db = _bump(rho, cfg.dome_flat_top)
            grad = torch.stack([db * drho_dx / ax, db * drho_dy / ay], 1)
        out_b.append(b)
        out_g.append(grad)
    (b1, b2), (g1, g2) = out_b, out_g
    depth = cfg.dome_depth * (1.0 - (1.0 - b1) * (1.0 - b2))
    grad = cfg.dome_depth * ((1.0 - b2)[:, None] * g1 + (1.0 - b1)[:, None] * g2)
    return depth, grad


def stack_height(cfg: StampFormingConfig) -> float:
    """e3 of the top ply's mid-plane in the initial state (the bottom ply is at 0)."""
    return (cfg.num_plies - 1) * cfg.ply_thickness


def die_surface(xy: Tensor, cfg: StampFormingConfig) -> tuple[Tensor, Tensor]:
    """Die top surface ``z_d(x, y)`` (touching the bottom ply's lower face) and its gradient."""
    depth, grad = dome_depth(xy, cfg, grow=cfg.die_clearance)
    return -0.5 * cfg.ply_thickness - depth, -grad


def punch_travel(t: Tensor | float, cfg: StampFormingConfig) -> Tensor | float:
    """Punch displacement along -e3 at time ``t`` (linear in time, ``stroke`` at ``duration``)."""
    if isinstance(t, Tensor):
        return cfg.stroke * (t / cfg.duration).clamp(0.0, 1.0)
    return cfg.stroke * min(max(t / cfg.duration, 0.0), 1.0)


def punch_surface(xy: Tensor, travel: float, cfg: StampFormingConfig) -> tuple[Tensor, Tensor]:
    """Punch lower surface ``z_p(x, y)`` after moving ``travel`` mm down, and its gradient.

    At ``travel = 0`` the dome apex is ``punch_clearance`` mm above the top ply's upper face.
    """
    depth, grad = dome_depth(xy, cfg)
    top = stack_height(cfg) + 0.5 * cfg.ply_thickness + cfg.punch_clearance + cfg.dome_depth
    return top - travel - depth, -grad
