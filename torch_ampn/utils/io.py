"""File helpers: atomic writes (no half-written file is ever left behind) and checked reads."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import torch


def _umask() -> int:
    """The process's file-mode creation mask, read without changing it where Linux tells it."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)  # elsewhere: read by setting it, and set it back at once
    os.umask(mask)
    return mask


def plain_mode(path: str | os.PathLike, folder: bool = False) -> None:
    """Give ``path`` the mode a plain ``open`` (or ``mkdir``) would: 0666 (0777) less the umask.

    ``tempfile`` makes its files 0600 and its folders 0700, and a rename keeps the mode, so
    without this an atomically written dataset could not be read by the owner's colleagues.
    """
    os.chmod(path, (0o777 if folder else 0o666) & ~_umask())


@contextlib.contextmanager
def _atomic_file(path: str | os.PathLike, mode: str) -> Iterator[IO]:
    """An open temporary file beside ``path`` that replaces it when the block ends without error."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        plain_mode(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_torch_save(obj: object, path: str | os.PathLike) -> None:
    """``torch.save(obj, path)`` through a temporary file in the same folder and a rename.

    Readers see either the old file or the complete new one; on any error the temporary
    file is removed and ``path`` is left as it was.
    """
    with _atomic_file(path, "wb") as f:
        torch.save(obj, f)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename."""
    with _atomic_file(path, "w") as f:
        f.write(text)


def atomic_savefig(fig: object, path: str | os.PathLike, dpi: int = 110) -> None:
    """``fig.savefig(path)`` (a matplotlib figure; the format from the suffix) through a temporary file."""
    path = Path(path)
    with _atomic_file(path, "wb") as f:
        fig.savefig(f, dpi=dpi, format=path.suffix.lstrip(".") or "png")


@contextlib.contextmanager
def atomic_folder(folder: str | os.PathLike, prefix: str = ".tmp-") -> Iterator[Path]:
    """A temporary folder beside ``folder`` to write into; it replaces ``folder`` when the block ends.

    On any error the temporary folder is removed and ``folder`` is left as it was.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=prefix))
    try:
        yield tmp
        plain_mode(tmp, folder=True)
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def load_torch_file(path: str | os.PathLike, kind: str) -> object:
    """``torch.load(path, weights_only=True)`` on the CPU; ``ValueError`` with one readable line if it fails.

    Args:
        path: The file.
        kind: What the file should be, for the message (e.g. ``"trajectory file"``).
    """
    if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; a cut one has no directory
        raise ValueError(f"{path}: not a readable {kind} (truncated, or not written by torch.save)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - corrupt members, objects weights-only loading refuses
        reason = " ".join(str(err).split())[:160]
        raise ValueError(f"{path}: not a readable {kind} ({type(err).__name__}: {reason})") from None
