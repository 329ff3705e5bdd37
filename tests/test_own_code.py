import types

import pytest
import torch

from torch_ampn.utils.own_code import own_code


def _scaled(x, factor=2.0, *, shift=0.0):
    return x * factor + shift


class _Model:
    def __init__(self, weight: float) -> None:
        self.weight = weight

    def apply(self, x):
        return x * self.weight


def test_own_code_copies_functions_closures_and_methods():
    copy = own_code(_scaled)
    assert copy.__code__ is not _scaled.__code__ and copy.__code__ == _scaled.__code__
    assert copy(3.0) == 6.0 and copy(3.0, 3.0, shift=1.0) == 10.0  # defaults and keyword defaults
    assert copy.__qualname__ == _scaled.__qualname__

    def make(k):
        def inner(x):
            return x + k

        return inner

    a, b = own_code(make(1)), own_code(make(2))
    assert a.__code__ is not b.__code__ and (a(0), b(0)) == (1, 2)  # each keeps its closure
    model = _Model(3.0)
    bound = own_code(model.apply)
    assert isinstance(bound, types.MethodType) and bound.__self__ is model and bound(2.0) == 6.0
    with pytest.raises(TypeError, match="Python function or method"):
        own_code(torch.sin)


def test_keyed_copies_are_shared_per_key(monkeypatch):
    import torch_ampn.utils.own_code as module

    monkeypatch.setattr(module, "_KEYED", type(module._KEYED)())
    monkeypatch.setattr(module, "KEYED_COPIES", 2)
    a, b = own_code(_scaled, key="a"), own_code(_scaled, key="a")
    assert a is not b and a.__code__ is b.__code__ is not _scaled.__code__  # same key: same code
    other = own_code(_scaled, key="b")
    assert other.__code__ is not a.__code__ and other(1.0) == 2.0
    fresh = own_code(_scaled).__code__
    assert fresh is not a.__code__ and fresh is not other.__code__  # no key: always new
    own_code(_scaled, key="c")  # a third key pushes out the least recently used one ("a")
    assert own_code(_scaled, key="b").__code__ is other.__code__
    assert own_code(_scaled, key="a").__code__ is not a.__code__


def test_compiled_copies_keep_a_cache_each(monkeypatch):
    import torch._dynamo

    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 1)
    monkeypatch.setattr(torch._dynamo.config, "fail_on_recompile_limit_hit", True)
    models = [_Model(float(w)) for w in range(1, 4)]
    x = torch.arange(4.0)
    for m in models:  # another bound self each time: one code object would need 3 entries
        compiled = torch.compile(own_code(m.apply), backend="eager", dynamic=False)
        torch.testing.assert_close(compiled(x), x * m.weight)
    shared = [torch.compile(m.apply, backend="eager", dynamic=False) for m in models[:2]]
    shared[0](x)
    with pytest.raises(Exception, match="recompile_limit"):  # what own_code avoids
        shared[1](x)
