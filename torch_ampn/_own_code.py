"""Functions with a code object of their own, so that ``torch.compile`` keeps a cache per copy.

Dynamo keeps compiled code per *code object* and, after ``recompile_limit`` (8) entries, runs
that code object eagerly (with a warning). A function compiled again and again with other
closure variables, another bound ``self`` or other shapes (a :class:`~torch_ampn.FastRollout`
per mesh, the simulator's step per part of a family) shares one code object, so from the 9th
copy on it would run uncompiled, and whether a given call ran compiled would depend on what
the process did before. A copied code object gives every copy its own cache, freed with it.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)


def own_code(fn: F) -> F:
    """``fn`` (a function, closure or bound method) with an equal but distinct code object."""
    if isinstance(fn, types.MethodType):
        return types.MethodType(own_code(fn.__func__), fn.__self__)  # type: ignore[return-value]
    if not isinstance(fn, types.FunctionType):
        raise TypeError(f"own_code needs a Python function or method, got {type(fn).__name__}")
    code = fn.__code__.replace()  # equal, not the same object
    copy = types.FunctionType(code, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__, copy.__qualname__, copy.__doc__ = fn.__kwdefaults__, fn.__qualname__, fn.__doc__
    return copy  # type: ignore[return-value]
