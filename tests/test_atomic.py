"""Atomic writes: old content or complete new content, never half; full / read-only disks in one line."""

import errno
import os
from types import SimpleNamespace

import numpy as np
import pytest

from coin_cl import atomic
from coin_cl.atomic import OutputWriteError, atomic_write, write_text
from coin_cl.scene.io import write_png


def _half_then(err):
    def write(p):
        p.write_bytes(b"half")
        raise err

    return write


def test_replaces_and_leaves_no_temporary(tmp_path):
    write_text(tmp_path / "a.json", "old")
    write_text(tmp_path / "a.json", "new")
    assert (tmp_path / "a.json").read_text() == "new" and os.listdir(tmp_path) == ["a.json"]


def test_failed_write_keeps_the_old_file(tmp_path):
    write_text(tmp_path / "a.txt", "old")
    with pytest.raises(ValueError):
        atomic_write(tmp_path / "a.txt", _half_then(ValueError("writer bug")))
    assert (tmp_path / "a.txt").read_text() == "old" and os.listdir(tmp_path) == ["a.txt"]


@pytest.mark.parametrize("code,why", [(errno.ENOSPC, "disk is full"), (errno.EROFS, "read-only"),
                                      (errno.EACCES, "no write permission")])  # fmt: skip
def test_disk_errors_name_the_folder_and_leave_nothing(tmp_path, code, why):
    with pytest.raises(OutputWriteError, match=f"cannot write in {tmp_path}: the {why}|{why}") as e:
        atomic_write(tmp_path / "img.png", _half_then(OSError(code, os.strerror(code))))
    assert "\n" not in str(e.value) and "another output folder" in str(e.value)
    assert os.listdir(tmp_path) == []


def test_wrapped_disk_full_error_is_recognised(tmp_path, monkeypatch):
    # torch.save reports a full disk as RuntimeError("... file write failed"): the folder is asked
    monkeypatch.setattr(atomic.os, "statvfs", lambda p: SimpleNamespace(f_bavail=0, f_frsize=4096))
    with pytest.raises(OutputWriteError, match="disk is full"):
        atomic_write(tmp_path / "ckpt.pt", _half_then(RuntimeError("file write failed")))
    assert os.listdir(tmp_path) == []


def test_unwritable_folder_when_creating_it(tmp_path, monkeypatch):
    def mkdir(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(atomic.Path, "mkdir", mkdir)
    with pytest.raises(
        OutputWriteError, match=f"cannot write in {tmp_path / 'sub'}: the file system is read-only"
    ):
        write_png(tmp_path / "sub" / "x.png", np.zeros((2, 2, 3), np.uint8))


def test_real_full_device(tmp_path):
    """/dev/full returns ENOSPC on every write: a real kernel error, not a simulated one."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")

    def write(p):
        with open("/dev/full", "wb") as f:  # the payload goes to the full device
            f.write(b"x" * 4096)
            f.flush()

    with pytest.raises(OutputWriteError, match="disk is full"):
        atomic_write(tmp_path / "a.bin", write)
    assert os.listdir(tmp_path) == []
