"""One fallback for several compiled callables: the first compiler failure turns them all eager."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any


class EagerFallback:
    """Wraps compiled callables so that a compiler failure warns once and runs the eager code.

    ``torch.compile`` compiles at the first call, so a missing C++ compiler or an unsupported
    operation shows only then. Every callable wrapped by one ``EagerFallback`` shares its
    state: after the first failure all of them run their eager counterparts, so that a step
    never mixes compiled and eager parts by accident.

    Args:
        consequence: What the warning says happens next (e.g. ``"the fast rollout runs eagerly"``).

    Example::

        fallback = EagerFallback("the step runs eagerly")
        step = fallback.wrap(torch.compile(step_fn), step_fn)
    """

    def __init__(self, consequence: str) -> None:
        self.consequence = consequence
        self.failed = False

    def wrap(self, compiled: Callable[..., Any], eager: Callable[..., Any]) -> Callable[..., Any]:
        """``compiled`` while compiling works, else ``eager`` (same arguments, same result)."""

        def call(*args: Any, **kwargs: Any) -> Any:
            if not self.failed:
                try:
                    return compiled(*args, **kwargs)
                except Exception as err:  # noqa: BLE001 - any compiler failure: run eagerly
                    self.fail(err)
            return eager(*args, **kwargs)

        return call

    def fail(self, err: Exception) -> None:
        """Turn every wrapped callable eager, with one warning naming ``err``."""
        first = str(err).splitlines()[0] if str(err) else ""
        warnings.warn(
            f"torch.compile failed ({type(err).__name__}: {first}); {self.consequence}",
            RuntimeWarning,
            stacklevel=4,
        )
        self.failed = True
