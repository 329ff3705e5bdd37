"""The fast rollouts a surrogate keeps: built (and compiled) once per mesh, batch size and device."""

from __future__ import annotations

from collections import OrderedDict

import torch

from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData
from torch_ampn.rollout.fast import FastRollout

#: How many :func:`cached_fast_rollout` keeps per surrogate (each holds its compiled code and its hierarchy).
CACHE_SIZE = 8


class _RunnerCache(OrderedDict):
    """A surrogate's :class:`FastRollout` objects by (hierarchy, batch size, compile, device), newest last.

    It lives on the surrogate (``surrogate._fast_rollouts``), so it goes when the surrogate goes;
    copies and pickles of the surrogate start with an empty one (compiled code is not copied).
    """

    def __deepcopy__(self, memo: dict) -> _RunnerCache:
        return _RunnerCache()

    def __reduce__(self) -> tuple:
        return (_RunnerCache, ())


def cached_fast_rollout(
    surrogate: AMPNSurrogate,
    hierarchy: HierarchicalData,
    batch_size: int = 1,
    compile: bool = True,
    device: torch.device | str | None = None,
) -> FastRollout:
    """A :class:`FastRollout` for these arguments, built at the first call and reused after.

    Reuse matters: building one compiles its step again. The surrogate keeps its last
    :data:`CACHE_SIZE` (a validation loop over one mesh builds one); they are released with it.
    """
    dev = torch.device(device) if device is not None else next(surrogate.parameters()).device
    cache = surrogate.__dict__.get("_fast_rollouts")
    if cache is None:
        cache = surrogate.__dict__["_fast_rollouts"] = _RunnerCache()
    key = (id(hierarchy), batch_size, compile, str(dev))
    runner = cache.get(key)
    if runner is None or runner.source is not hierarchy:
        runner = FastRollout(surrogate, hierarchy, batch_size=batch_size, compile=compile, device=dev)
        cache[key] = runner
        while len(cache) > CACHE_SIZE:
            cache.popitem(last=False)
    cache.move_to_end(key)
    return runner
