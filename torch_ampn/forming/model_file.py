"""Model files: a surrogate's constructor arguments and weights, readable without Lightning."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from torch_ampn.utils.io import atomic_torch_save, load_torch_file

#: The ``format`` field of a model file (:meth:`ModelFile.save`) and its version.
MODEL_FILE_FORMAT, MODEL_FILE_VERSION = "torch-ampn surrogate", 1


def _read(path: str | os.PathLike) -> dict[str, Any]:
    """A model file's payload, its ``format`` and ``version`` checked (one-line errors)."""
    payload = load_torch_file(path, "torch-ampn model file")
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FILE_FORMAT:
        raise ValueError(
            f"{path}: not a torch-ampn model file (field 'format'); write one with torch-ampn export"
        )
    if int(payload.get("version", 0)) > MODEL_FILE_VERSION:
        version = payload["version"]
        raise ValueError(f"{path}: field 'version': {version} is newer than this torch-ampn reads")
    return payload


def load_surrogate(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> Any:
    """The surrogate of any model file, of the class its ``kind`` field names, in eval mode.

    ``torch-ampn export`` writes next-step (:class:`~torch_ampn.forming.AMPNSurrogate`) and
    direct (:class:`~torch_ampn.forming.DirectSurrogate`) models alike; this reads either, and
    :func:`torch_ampn.rollout.rollout` predicts a trajectory with either.

    Example:
        >>> surrogate = load_surrogate("model.pt")  # doctest: +SKIP
        >>> type(surrogate).__name__  # doctest: +SKIP
        'DirectSurrogate'

    Raises:
        ValueError: One line naming the file and field, if it is not a readable model file.
    """
    from torch_ampn.forming.direct import DirectSurrogate
    from torch_ampn.forming.surrogate import AMPNSurrogate

    kinds: dict[str, type[ModelFile]] = {c.__name__: c for c in (AMPNSurrogate, DirectSurrogate)}
    kind = _read(path).get("kind", "AMPNSurrogate")
    if kind not in kinds:
        raise ValueError(f"{path}: field 'kind': {kind!r} is not one of {sorted(kinds)}")
    return kinds[kind].load(path, map_location)


class ModelFile:
    """Mixin of the surrogates: :meth:`save` and :meth:`load` of a model file.

    The class needs :attr:`arguments` (its constructor's arguments, JSON-serialisable) and
    :attr:`meta`; the file records the class name (field ``kind``), and :meth:`load` refuses a
    file of another kind. Files without the field are :class:`~torch_ampn.forming.AMPNSurrogate`'s.
    """

    arguments: dict[str, Any]
    meta: dict[str, Any]

    def save(self, path: str | os.PathLike, meta: dict[str, Any] | None = None) -> Path:
        """Write a model file: the constructor's arguments and ``meta`` as JSON, and the weights.

        :meth:`load` reads it back with ``torch.load(weights_only=True)`` and without Lightning
        (``torch-ampn export`` writes one from a Lightning checkpoint). The file is written
        atomically.

        Args:
            path: The file (``.pt``).
            meta: JSON-serialisable facts to keep with the model (default: :attr:`meta`).

        Raises:
            ValueError: If an argument is not JSON-serialisable (e.g. an aggregation module).
        """
        try:
            arguments = json.dumps(self.arguments)
            facts = json.dumps(self.meta if meta is None else meta)
        except TypeError as err:
            raise ValueError(f"{path}: the surrogate's arguments cannot be written as JSON ({err})") from None
        payload = {
            "format": MODEL_FILE_FORMAT,
            "version": MODEL_FILE_VERSION,
            "kind": type(self).__name__,
            "arguments": arguments,
            "meta": facts,
            "state_dict": {  # tensors, and a module's extra state as it is
                k: v.detach().cpu() if isinstance(v, torch.Tensor) else v
                for k, v in self.state_dict().items()  # type: ignore[attr-defined]
            },
        }
        atomic_torch_save(payload, path)
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike, map_location: str | torch.device = "cpu") -> Any:
        """The surrogate of a model file from :meth:`save`, in eval mode (no Lightning needed).

        Raises:
            ValueError: One line naming the file and field, if it is not a readable model file
                of this class.
        """
        payload = _read(path)
        kind = payload.get("kind", "AMPNSurrogate")
        if kind != cls.__name__:
            raise ValueError(
                f"{path}: field 'kind': a {kind} model, not a {cls.__name__} "
                f"(use {kind}.load, or load_surrogate for any kind)"
            )
        try:
            arguments, meta = json.loads(payload["arguments"]), json.loads(payload["meta"])
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path}: field 'arguments' or 'meta' is not JSON ({err})") from None
        try:
            surrogate = cls(**arguments)
            surrogate.load_state_dict(payload["state_dict"])  # type: ignore[attr-defined]
        except (TypeError, ValueError, RuntimeError, KeyError) as err:
            reason = " ".join(str(err).split())[:200]
            raise ValueError(f"{path}: field 'state_dict' does not fit the arguments ({reason})") from None
        surrogate.meta = meta
        return surrogate.to(map_location).eval()  # type: ignore[attr-defined]
