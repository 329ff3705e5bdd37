r"""Autoregressive rollout of a whole trajectory, and its error metric.

A rollout starts from a trajectory's initial state and repeats, for ``t = 1 .. T``:
build the window ``(t-1, t)`` from the *predicted* positions (:func:`~torch_ampn.data.step_sample`),
rebuild the contact edges on every level from those positions, predict the residual
:math:`\Delta\tilde u^t` and set :math:`\tilde u^t = \tilde u^{t-1} + \Delta\tilde u^t` on ply nodes.
Tool nodes follow their prescribed motion (the trajectory's tool positions) exactly.

The predictor is any callable ``HierarchicalData -> Tensor[N, 3]`` (residual in mm of every
``l0`` node): :meth:`~torch_ampn.forming.AMPNSurrogate.predict_residual` or a baseline of
:mod:`torch_ampn.baselines`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch
from torch import Tensor

from torch_ampn.data.dataset import step_sample
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.utils.threads import follow_free_cpu

Predictor = Callable[[HierarchicalData], Tensor]
Transform = Callable[[HierarchicalData], HierarchicalData]


def _on_device(
    traj: Trajectory, hierarchy: HierarchicalData, device: torch.device | str | None
) -> tuple[Trajectory, HierarchicalData, torch.device]:
    """``traj`` and ``hierarchy`` on ``device`` (default: the hierarchy's); the caller's copies untouched."""
    if device is None:
        device = hierarchy.mesh(0).edge_index.device
    device = torch.device(device)
    if hierarchy.mesh(0).edge_index.device != device:
        hierarchy = hierarchy.clone().to(device)  # .to() works in place: keep the caller's copy
    return traj.to(device), hierarchy, device


@torch.no_grad()
def rollout_plain(
    predictor: Predictor,
    traj: Trajectory,
    hierarchy: HierarchicalData,
    contact: Transform | None = None,
    num_steps: int | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    start: int = 0,
    bundle_steps: int = 1,
) -> Tensor:
    """Roll ``predictor`` out over ``traj`` from its initial state, window by window.

    The plain path of :func:`torch_ampn.rollout.rollout` (``fast=False``), whose docstring gives
    the arguments; returns the predicted positions ``[num_steps + 1, N, 3]`` (float32, CPU).
    ``start``: roll out from the true state at this step instead (rows ``0 .. start`` are the
    trajectory's own): how the error grows from a correct state halfway through the forming.
    ``bundle_steps`` ``B``: the predictor returns the offsets of the next ``B`` steps from the
    current state, ``[N, 3 B]`` (a bundled :class:`~torch_ampn.forming.AMPNSurrogate`), and
    the rollout moves ``B`` steps per call.
    """
    steps = traj.num_steps if num_steps is None else num_steps
    if not 1 <= steps <= traj.num_steps:
        raise ValueError(f"num_steps must be in 1..{traj.num_steps}, got {steps}")
    if not 0 <= start < steps:
        raise ValueError(f"start must be in 0..{steps - 1}, got {start}")
    if bundle_steps < 1:
        raise ValueError(f"bundle_steps must be >= 1, got {bundle_steps}")
    traj, hierarchy, device = _on_device(traj, hierarchy, device)
    ply = traj.ply_mask  # [N]
    # Prediction buffer: tools on their prescribed path, plies at rest until predicted.
    pred = traj.pos.clone().float()  # [T+1, N, 3]
    pred[start + 1 :, ply] = pred[start, ply]
    state = dataclasses.replace(traj, pos=pred)
    iterator = range(start + 1, steps + 1, bundle_steps)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc="rollout", unit="step", leave=False)
    # edges from the initial state (ComponentRadiusGraph(positions="initial")) are built once
    static_contact = getattr(contact, "positions", "current") == "initial"
    with follow_free_cpu(device) as threads:  # spinning threads, as many as other processes leave cores
        edges: list[Tensor] | None = None
        for t in iterator:
            threads.step()
            data = step_sample(state, t, hierarchy, bundle_steps)
            if edges is not None:
                for level, edge_index in enumerate(edges):
                    data.contact(level).edge_index = edge_index
            elif contact is not None:
                data = contact(data)
                if static_contact:
                    edges = [data.contact(level).edge_index for level in range(data.num_levels)]
            _place_call(pred, t, steps, ply, pred[t - 1], predictor(data), bundle_steps)
    return pred[: steps + 1].cpu()


def _place_call(
    pred: Tensor, t: int, steps: int, ply: Tensor, before: Tensor, du: Tensor, bundle_steps: int
) -> None:
    """Write one call's ``B`` steps into ``pred`` ``[T+1, N, 3]``: rows ``t .. t + B - 1``, at most ``steps``.

    ``du`` ``[N, 3 B]`` holds the offsets from ``before`` (:math:`x^{t-1}`) on ply nodes; tool
    rows keep what ``pred`` holds (their prescribed path).
    """
    if du.size(-1) != 3 * bundle_steps:
        raise ValueError(
            f"the predictor returned {du.size(-1)} columns per node; bundle_steps={bundle_steps} "
            f"needs {3 * bundle_steps}"
        )
    du = du.float()
    for k in range(min(bundle_steps, steps + 1 - t)):
        pred[t + k] = next_positions(ply, before, du[:, 3 * k : 3 * k + 3], pred[t + k])


@torch.no_grad()
def one_step_predictions(
    predictor: Predictor,
    traj: Trajectory,
    hierarchy: HierarchicalData,
    contact: Transform | None = None,
    device: torch.device | str | None = None,
    bundle_steps: int = 1,
) -> Tensor:
    """Teacher-forced predictions: each step ``t`` predicted from the *true* states ``t-1, t-2``.

    Row ``t`` of the result ``[T+1, N, 3]`` (float32, CPU) is the true state ``t - 1`` moved by
    the predicted residual on ply nodes (tools on their path; row 0 the initial state). Its
    error is the single step's, with no error carried over: against :func:`rollout_plain`'s,
    it tells a wrong step from an error that compounds over the rollout. A bundled predictor
    (``bundle_steps`` ``B``) is called at ``t = 1, 1 + B, ...`` from the true state before,
    and fills the ``B`` rows of its call: the error of one call, none carried between calls.
    """
    traj, hierarchy, device = _on_device(traj, hierarchy, device)
    ply = traj.ply_mask  # [N]
    pred = traj.pos.clone().float()  # [T+1, N, 3]
    steps = traj.num_steps
    for t in range(1, steps + 1, bundle_steps):
        data = step_sample(traj, t, hierarchy, bundle_steps)
        if contact is not None:
            data = contact(data)
        _place_call(pred, t, steps, ply, traj.pos[t - 1].float(), predictor(data), bundle_steps)
    return pred.cpu()


def next_positions(ply: Tensor, pos: Tensor, residual: Tensor, tool_next: Tensor) -> Tensor:
    """The positions at step ``t`` ``[N, 3]``, the update of every rollout.

    Ply nodes (``ply``, ``BoolTensor[N]``) move by ``residual`` from ``pos`` (step ``t - 1``);
    tool nodes are on their prescribed path ``tool_next``.
    """
    return torch.where(ply[:, None], pos + residual.float(), tool_next)


def rollout_rmse(pred: Tensor, true: Tensor, mask: Tensor | None = None) -> Tensor:
    r"""RMSE per step between predicted and true positions (seed paper, "Results"), ``[T+1]``.

    :math:`\mathrm{RMSE}_t = \sqrt{\frac{1}{3 N} \sum_{i, j} (\tilde u_{ij}^t - u_{ij}^t)^2}` over the
    ``N`` nodes selected by ``mask`` (ply nodes) and their 3 coordinates; average rows
    ``1 .. T`` for the paper's per-trajectory number (row 0, the given initial state, is 0).

    Args:
        pred: Predicted positions ``[T+1, N, 3]``.
        true: True positions, same shape (its first ``T+1`` steps are used if longer).
        mask: ``BoolTensor[N]`` nodes to compare (default: all).
    """
    true = true[: pred.size(0)]
    if pred.shape != true.shape:
        raise ValueError(f"pred {list(pred.shape)} and true {list(true.shape)} must have the same shape")
    diff = pred.double() - true.double().to(pred.device)  # [T+1, N, 3]
    if mask is not None:
        diff = diff[:, mask.to(pred.device)]
    return diff.square().mean(dim=(1, 2)).sqrt().float()
