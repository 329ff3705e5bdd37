"""Atomic writes: a reader sees the old file or folder or the complete new one, never a part."""

import pytest
import torch

from torch_ampn.utils.io import atomic_folder, atomic_torch_save, atomic_write_text


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_atomic_folder_replaces_on_success_and_keeps_the_old_one_on_error(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_folder(out, prefix=".tmp-test-") as tmp:
        assert tmp.parent == tmp_path and tmp != out
        (tmp / "new.txt").write_text("new")
        assert (out / "old.txt").read_text() == "old"  # untouched until the block ends
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    with pytest.raises(RuntimeError, match="disk full"):
        with atomic_folder(out, prefix=".tmp-test-") as tmp:
            (tmp / "half.txt").write_text("half")
            raise RuntimeError("disk full")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert _leftovers(tmp_path) == []


def test_atomic_files_keep_the_old_content_on_error(tmp_path):
    path = tmp_path / "a" / "x.pt"
    atomic_torch_save({"v": torch.arange(3)}, path)
    assert torch.load(path)["v"].tolist() == [0, 1, 2]

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("cannot pickle")

    with pytest.raises(RuntimeError, match="cannot pickle"):
        atomic_torch_save({"v": Unpicklable()}, path)
    assert torch.load(path)["v"].tolist() == [0, 1, 2]
    text = tmp_path / "t.txt"
    atomic_write_text(text, "one")
    atomic_write_text(text, "two")
    assert text.read_text() == "two"
    assert _leftovers(tmp_path / "a") == [] and sorted(p.name for p in tmp_path.iterdir()) == ["a", "t.txt"]


def test_written_files_get_the_mode_a_plain_open_gives(tmp_path):
    """Not tempfile's 0600 / 0700: colleagues in the group may read a shared dataset."""
    import os
    import stat

    old = os.umask(0o027)  # this test sets the mask itself, and puts it back
    try:
        (tmp_path / "plain.txt").write_text("x")
        (tmp_path / "plain").mkdir()
        atomic_write_text(tmp_path / "a.txt", "x")
        atomic_torch_save({"x": torch.zeros(1)}, tmp_path / "b.pt")
        with atomic_folder(tmp_path / "folder") as tmp:
            (tmp / "c.txt").write_text("x")
    finally:
        os.umask(old)
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(tmp_path / "plain.txt") == 0o640 and mode(tmp_path / "plain") == 0o750
    assert mode(tmp_path / "a.txt") == mode(tmp_path / "b.pt") == 0o640
    assert mode(tmp_path / "folder") == 0o750 and mode(tmp_path / "folder" / "c.txt") == 0o640
