"""Atomic writes: old content or complete new content, never half; full / read-only disks in one line."""

import errno
import os
import stat
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


def test_a_planted_file_link_is_not_followed(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / "plan.json").symlink_to(outside)
    with atomic.confined_to(out), pytest.raises(atomic.UnsafePathError, match="symbolic link") as e:
        write_text(out / "plan.json", "{}")
    assert str(out / "plan.json") in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(atomic.UnsafePathError):  # refused without a declared output folder too
        write_png(out / "plan.json", np.zeros((2, 2), np.uint8))
    assert outside.read_text() == "precious" and (out / "plan.json").is_symlink()
    assert [p.name for p in out.iterdir()] == ["plan.json"]  # no temporary left


def test_a_planted_folder_link_inside_the_output_folder_is_not_followed(tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "depth.npy").write_bytes(b"theirs")
    out = tmp_path / "out"
    (out / "eval").mkdir(parents=True)
    (out / "eval" / "depth").symlink_to(outside, target_is_directory=True)
    with atomic.confined_to(out):
        with pytest.raises(atomic.UnsafePathError, match=r"the folder .*depth is a symbolic link"):
            write_text(out / "eval" / "depth" / "depth.npy", "mine")
        with pytest.raises(atomic.UnsafePathError):  # a new file through the link: refused too
            atomic.write_bytes(out / "eval" / "depth" / "new" / "x.npy", b"mine")
        write_text(out / "eval" / "ok.json", "{}")  # a plain folder is fine
    assert sorted(p.name for p in outside.iterdir()) == ["depth.npy"]
    assert (outside / "depth.npy").read_bytes() == b"theirs"


def test_the_output_folder_itself_may_sit_under_a_link(tmp_path):
    """The user's own --out path may go through a link (/tmp on macOS); only what is inside it may not."""
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "via").symlink_to(real, target_is_directory=True)
    out = tmp_path / "via" / "out"
    with atomic.confined_to(out):
        write_text(out / "a" / "b.txt", "x")
    assert (real / "out" / "a" / "b.txt").read_text() == "x"


def test_copy_file_is_atomic_and_refuses_links(tmp_path):
    src = tmp_path / "src.bin"
    src.write_bytes(b"abc")
    atomic.copy_file(src, tmp_path / "dst.bin")
    assert (tmp_path / "dst.bin").read_bytes() == b"abc"
    (tmp_path / "link.bin").symlink_to(src)
    with pytest.raises(atomic.UnsafePathError):
        atomic.copy_file(tmp_path / "dst.bin", tmp_path / "link.bin")
    assert src.read_bytes() == b"abc"


def test_outputs_get_the_users_file_mode_not_mkstemps_0600(tmp_path):
    mask = os.umask(0o022)  # read the process's umask (and put it back at once)
    os.umask(mask)
    write_text(tmp_path / "page.html", "<p>hi</p>")
    mode = stat.S_IMODE((tmp_path / "page.html").stat().st_mode)
    assert mode == 0o666 & ~mask
    assert mask & 0o044 or mode & 0o044  # readable by others unless the umask forbids it


def test_refuse_links_names_the_first_link_and_skips_what_it_is_told(tmp_path):
    out = tmp_path / "out"
    (out / "a" / "b").mkdir(parents=True)
    (out / "a" / "b" / "f.txt").write_text("x")
    atomic.refuse_links(out)  # no link: nothing to say
    atomic.refuse_links(tmp_path / "absent")
    (out / "photos").symlink_to(tmp_path, target_is_directory=True)
    atomic.refuse_links(out, skip=("photos",))  # the photos a command only reads
    with pytest.raises(atomic.UnsafePathError, match="symbolic link") as e:
        atomic.refuse_links(out)
    assert str(e.value).startswith(f"refusing to write {out / 'photos'}: it is a symbolic link")
    (out / "photos").unlink()
    (out / "a" / "b" / "g.txt").symlink_to(tmp_path / "nowhere")  # a dangling file link too
    with pytest.raises(atomic.UnsafePathError, match=str(out / "a" / "b" / "g.txt")):
        atomic.refuse_links(out)
