"""Random generators' states in a checkpoint: a resumed fit draws what the stopped one would have."""

from __future__ import annotations

from typing import Any

import torch


def rng_states() -> dict[str, Any]:
    """The states of torch's CPU generator and, where CUDA is in use, of every CUDA device's."""
    states: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def restore_rng_states(states: dict[str, Any]) -> None:
    """Set the generators to ``states`` (of :func:`rng_states`); CUDA states only for as many devices."""
    if "torch" in states:
        torch.set_rng_state(states["torch"])
    cuda = torch.cuda.is_available() and len(states.get("cuda", ())) == torch.cuda.device_count()
    if "cuda" in states and cuda:
        torch.cuda.set_rng_state_all(states["cuda"])
