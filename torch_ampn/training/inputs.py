r"""What the loss sees of a training batch: training noise and the pushforward trick.

Both work in place on a (batched) window of :func:`~torch_ampn.data.step_sample` and return it.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from torch import Tensor

from torch_ampn.data.dataset import set_window
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData


def add_training_noise(
    data: HierarchicalData,
    sigma_x: float,
    position_noise: float,
    residual_noise: float,
    correct_target: bool = True,
    correlated_noise: bool = False,
) -> HierarchicalData:
    r"""Perturb ply positions and previous residuals with Gaussian noise, in place.

    Ply positions get :math:`\epsilon \sim N(0, (\text{position\_noise}\,\sigma_x)^2)` and previous
    residuals :math:`N(0, (\text{residual\_noise}\,\sigma_x)^2)` (tools are left exact). With
    ``correct_target`` the target residual becomes :math:`x^t - (x^{t-1} + \epsilon)`; with
    ``correlated_noise`` the previous residual gets :math:`\epsilon` as well (plus its own noise).

    Args:
        data: Window(s) with ``l0``'s ``pos``, ``prev_disp``, ``target`` ``[N, 3]`` and ``ply_mask``.
        sigma_x: :math:`\sigma_x`, the standard deviation of training node positions (mm).
        position_noise: Position noise in units of :math:`\sigma_x` (0: none).
        residual_noise: Previous-residual noise in units of :math:`\sigma_x` (0: none).
        correct_target: Let the target undo the position noise.
        correlated_noise: Add the position noise to the previous residual too.
    """
    fine = data["l0"]
    ply = fine.ply_mask[:, None].to(fine.pos.dtype)  # [N, 1]
    if position_noise > 0:
        eps = ply * (position_noise * sigma_x) * torch.randn_like(fine.pos)  # [N, 3]
        fine.pos = fine.pos + eps
        if correct_target:  # every bundled offset starts from the perturbed x^{t-1}
            fine.target = fine.target - eps.repeat(1, fine.target.size(-1) // 3)
        if correlated_noise:
            fine.prev_disp = fine.prev_disp + eps
    if residual_noise > 0:
        fine.prev_disp = fine.prev_disp + ply * (residual_noise * sigma_x) * torch.randn_like(fine.pos)
    return data


def pushforward_inputs(
    data: HierarchicalData, predict_residual: Callable[[HierarchicalData], Tensor]
) -> HierarchicalData:
    r"""Replace the true :math:`x^{t-1}` of ply nodes by the prediction from :math:`x^{t-2}`, in place.

    The window ``(t-2, t-1)`` is built with :func:`~torch_ampn.data.set_window` from the
    fields :func:`~torch_ampn.data.step_sample` provides (``prev_disp``, ``prev_prev_disp``,
    ``prev_gripper_*``; its contact edges are those of :math:`x^{t-1}`); with the predicted
    :math:`\widehat{\Delta u}^{t-1}` (no gradient) and its error
    :math:`e = \widehat{\Delta u}^{t-1} - \Delta u^{t-1}` on ply nodes of windows with
    ``t >= 2``: ``pos`` :math:`+ e`, ``prev_disp`` :math:`+ e`, ``target`` :math:`- e`.

    Args:
        data: Window(s) of :func:`~torch_ampn.data.step_sample` (one or a batch).
        predict_residual: The model's residual ``[N, 3]`` of a window (e.g.
            :meth:`AMPNSurrogate.predict_residual <torch_ampn.forming.AMPNSurrogate.predict_residual>`).
    """
    fine = data["l0"]
    before = set_window(
        copy.copy(data),
        pos=fine.pos - fine.prev_disp,  # x^{t-2}
        prev_disp=fine.prev_prev_disp,
        next_disp=fine.prev_disp,
        ply_mask=fine.ply_mask,
        gripper_pos=data.prev_gripper_pos,
        gripper_force=data.prev_gripper_force,
        prior_pos=fine.get("prior_before"),
        prior_next=fine.get("prior_pos"),
    )
    with torch.no_grad():
        predicted = predict_residual(before).to(fine.pos.dtype)  # [N, 3]
    step = data.step[fine.batch] if "batch" in fine else data.step.expand(fine.num_nodes)  # [N]
    moved = fine.ply_mask & (step >= 2)  # [N]
    error = torch.where(moved[:, None], predicted - fine.prev_disp, torch.zeros_like(predicted))
    fine.pos = fine.pos + error
    fine.prev_disp = fine.prev_disp + error
    fine.target = fine.target - error
    return data
