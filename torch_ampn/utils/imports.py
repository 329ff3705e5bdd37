"""Objects named by an import path in a config (``"package.module:name"``), with one-line errors."""

from __future__ import annotations

import importlib
from typing import Any


def import_object(path: str, setting: str) -> Any:
    """The object ``"package.module:name"`` (or ``"package.module.name"``) names.

    Args:
        path: The import path.
        setting: The config setting it came from, named in the error (e.g. ``"network_class"``).

    Raises:
        ValueError: One line naming ``setting`` where the path is malformed, the module does not
            import or has no such name.
    """
    module_name, sep, name = path.partition(":")
    if not sep:
        module_name, _, name = path.rpartition(".")
    if not module_name or not name:
        raise ValueError(f"{setting}: {path!r} is not 'package.module:name'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ValueError(f"{setting}: cannot import {module_name!r} ({err})") from None
    if not hasattr(module, name):
        raise ValueError(f"{setting}: {module_name!r} has no {name!r}")
    return getattr(module, name)
