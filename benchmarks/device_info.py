"""What a device is, in words, for benchmark records (the CPU's model name, not just ``x86_64``)."""

from __future__ import annotations

import platform
from pathlib import Path

import torch

#: CPU flags named in :func:`device_name`, widest first (the first one present is named).
_VECTOR_FLAGS = (("amx_tile", "AMX"), ("avx512f", "AVX-512"), ("avx2", "AVX2"))


def device_name(device: torch.device | str = "cpu", cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The GPU's name (``torch.cuda.get_device_name``) or the CPU's model name and widest vector unit.

    On Linux the CPU's comes from ``/proc/cpuinfo`` (``model name``, and e.g. ``AVX2`` from its
    flags: Inductor's kernels and the matrix products depend on it), where
    ``platform.processor()`` is often empty; elsewhere ``platform.processor()`` or the
    architecture. Example: ``"AMD EPYC (family 25, model 1, AVX2)"``.

    Args:
        device: The device (a CUDA device gives the GPU's name).
        cpuinfo: The file to read the CPU from.
    """
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        info: dict[str, str] = {}
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            if not key.strip() and info:
                break  # the first processor is enough
            info.setdefault(key.strip(), value.strip())
        flags = set(info.get("flags", "").split())
        vector = next((name for flag, name in _VECTOR_FLAGS if flag in flags), None)
        details = [f"family {info['cpu family']}, model {info['model']}"] if "cpu family" in info else []
        details += [vector] if vector else []
        if info.get("model name"):
            return info["model name"] + (f" ({', '.join(details)})" if details else "")
    except (OSError, KeyError):
        pass
    return platform.processor() or platform.machine() or "cpu"
