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
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import TypeVar

F = TypeVar("F", bound=Callable)

#: Code copies by (original code object, key), newest last (see :func:`own_code`).
_KEYED: OrderedDict[tuple[types.CodeType, Hashable], types.CodeType] = OrderedDict()
#: How many keyed copies are kept (each with the compiled code Dynamo attached to it).
KEYED_COPIES = 16


def own_code(fn: F, key: Hashable | None = None) -> F:
    """``fn`` (a function, closure or bound method) with an equal but distinct code object.

    Args:
        fn: The function.
        key: Without one, a new code object every call. With one, the same code object for
            the same ``fn`` and key (the last :data:`KEYED_COPIES` kept), so that calls that
            build ``fn`` again for the same shapes (the simulator's step of one mesh) reuse
            Dynamo's compiled code instead of tracing it again.
    """
    if isinstance(fn, types.MethodType):
        return types.MethodType(own_code(fn.__func__, key), fn.__self__)  # type: ignore[return-value]
    if not isinstance(fn, types.FunctionType):
        raise TypeError(f"own_code needs a Python function or method, got {type(fn).__name__}")
    if key is None:
        code = fn.__code__.replace()  # equal, not the same object
    else:
        code = _KEYED.pop((fn.__code__, key), None) or fn.__code__.replace()
        _KEYED[(fn.__code__, key)] = code
        while len(_KEYED) > KEYED_COPIES:
            _KEYED.popitem(last=False)
    copy = types.FunctionType(code, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__, copy.__qualname__, copy.__doc__ = fn.__kwdefaults__, fn.__qualname__, fn.__doc__
    return copy  # type: ignore[return-value]
