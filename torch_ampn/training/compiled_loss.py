"""The surrogate's training loss through a ``torch.compile``'d network, falling back to eager."""

from __future__ import annotations

import torch
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor

from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.utils.threads import GOVERNOR


class CompiledLoss:
    """``surrogate.loss(data)`` with the network compiled at the first call (``dynamic=True``).

    Where compiling fails it warns once and goes on eagerly, with the random generators
    rewound, so that the eager step draws the same noise as the failed one. Not a module:
    the compiled wrapper stays out of the state dict and of weight averaging.

    Args:
        surrogate: The surrogate whose :meth:`~torch_ampn.forming.AMPNSurrogate.loss` is computed.
        enabled: Compile at all (``False``: always eager).
    """

    def __init__(self, surrogate: AMPNSurrogate, enabled: bool = True) -> None:
        self.surrogate = surrogate
        #: ``None``: not compiled yet; ``False``: eager (off or failed); else the compiled network.
        self.network = None if enabled else False

    def __call__(self, data: HierarchicalData) -> Tensor:
        """The loss of a (noised) batch."""
        if self.network is False:
            return self.surrogate.loss(data)
        if self.network is not None:
            return self.surrogate.loss(data, network=self.network)
        compiled = torch.compile(self.surrogate.diffusion.model, dynamic=True)
        device = data["l0"].pos.device
        rng = torch.get_rng_state(), torch.cuda.get_rng_state(device) if device.type == "cuda" else None
        try:
            with GOVERNOR.at_ceiling():  # its kernels are built for every thread torch may use
                loss = self.surrogate.loss(data, network=compiled)
        except Exception as err:  # noqa: BLE001 - any compiler failure: go on eager
            rank_zero_warn(
                f"compile_network: torch.compile failed ({type(err).__name__}: {str(err)[:300]}); "
                "training goes on without it"
            )
            self.network = False
            torch.set_rng_state(rng[0])  # the eager step draws the same noise as the failed one
            if rng[1] is not None:
                torch.cuda.set_rng_state(rng[1], device)
            return self.surrogate.loss(data)
        self.network = compiled
        return loss
