"""Atomic file writing: a file is either its old self or complete, never half written.

`atomic_write(path, write)` calls `write(tmp)` on a temporary name in the same folder (same file
system, so the rename is atomic), fsyncs it, renames it over `path` with `os.replace` and fsyncs
the folder, so that neither a kill (SIGKILL, power loss) nor a full disk leaves a truncated file
under the final name. The temporary names start with ".tmp-" so that the stage runner's hashes
(`coin_cl.pipeline.runner.hash_files`) ignore a leftover one.

A write that fails for want of room or permission (full disk, quota, read-only mount, no write
access) raises `OutputWriteError`: one line naming the folder and what to do.

Links are never followed (files come from anyone: a link planted in an output folder must not turn
a rerun into a write anywhere the user can write). A final path that is a symbolic link is refused;
inside an output folder declared with `confined_to(OUT)` (the CLI declares every command's --out),
a folder between OUT and the file that is a link, or that resolves outside OUT, is refused too:
`UnsafePathError`, one line naming the path. Only pure-stdlib imports, so every layer (diffusion/
included) may use it.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

TMP_PREFIX = ".tmp-"

# errno -> what it means for the user; anything else is re-raised as it is.
_DISK_ERRORS = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "no write permission",
    errno.EPERM: "no write permission",
}


class OutputWriteError(OSError):
    """An output could not be written (full or read-only disk, no permission); nothing was left
    half written."""

    def __str__(self) -> str:  # the message alone, without OSError's "[Errno N]" prefix
        return str(self.strerror)


class UnsafePathError(OutputWriteError):
    """An output path is, or goes through, a symbolic link (or leaves its output folder): refused."""


# Output folders declared by `confined_to` (absolute, not resolved: the user's own --out may sit
# under a link, such as /tmp on macOS; what lies inside it may not).
_ROOTS: list[Path] = []


@contextmanager
def confined_to(folder: str | Path) -> Iterator[None]:
    """`with confined_to(OUT):` writes under OUT refuse any folder on the way that is a link or
    resolves outside OUT (`check_path`)."""
    root = Path(os.path.abspath(folder))
    _ROOTS.append(root)
    try:
        yield
    finally:
        _ROOTS.remove(root)


def _refuse(path: Path, why: str) -> UnsafePathError:
    return UnsafePathError(
        errno.ELOOP,
        f"refusing to write {path}: {why}; coin-cl does not follow links in its output folders, "
        "remove the link or choose another output folder",
    )


def check_path(path: str | Path) -> Path:
    """`path` made absolute, after checking that writing it follows no link: `path` itself is not
    a symbolic link and, under a `confined_to` folder, no folder between it and `path` is one
    or resolves outside it. Raises `UnsafePathError` naming the path."""
    p = Path(os.path.abspath(path))
    if p.is_symlink():
        raise _refuse(p, f"it is a symbolic link (to {os.readlink(p)})")
    for root in _ROOTS:
        if not p.is_relative_to(root):
            continue
        real_root = os.path.realpath(root)
        folder = root
        for part in p.parent.relative_to(root).parts:
            folder = folder / part
            if folder.is_symlink():
                raise _refuse(p, f"the folder {folder} is a symbolic link (to {os.readlink(folder)})")
        real = os.path.realpath(p.parent)
        if os.path.commonpath([real, real_root]) != real_root:
            raise _refuse(p, f"its folder resolves to {real}, outside {root}")
    return p


def refuse_links(folder: str | Path, skip: tuple[str, ...] = ()) -> None:
    """Raise `UnsafePathError` naming the first symbolic link found under `folder` (links are not
    followed; `skip`: names directly in `folder` not looked into, e.g. the photos a command only
    reads). coin-cl makes no links, so one in its output folder was planted: a command refuses the
    folder before it clears, moves or writes anything there (a library's `rmtree` or `move` of a
    linked folder would act on the link's target)."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for here, dirs, files in os.walk(folder):
        if Path(here) == folder:
            dirs[:] = [d for d in dirs if d not in skip]
            files = [f for f in files if f not in skip]
        for name in sorted(dirs + files):
            p = Path(here) / name
            if p.is_symlink():
                raise _refuse(p, f"it is a symbolic link (to {os.readlink(p)})")


def disk_error(exc: OSError, folder: Path) -> OutputWriteError | None:
    """The one-line `OutputWriteError` for a full / read-only / forbidden `folder`, or None when
    `exc` is another kind of failure."""
    why = _DISK_ERRORS.get(exc.errno or -1)
    if why is None:
        return None
    todo = "free some space" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "make it writable"
    return OutputWriteError(
        exc.errno, f"cannot write in {folder}: {why}; {todo} or choose another output folder"
    )


def _full_disk(folder: Path) -> OutputWriteError | None:
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):
        return None
    if st.f_bavail * st.f_frsize < (1 << 16):
        return disk_error(OSError(errno.ENOSPC, "no space"), folder)
    return None


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # not possible everywhere (Windows); the rename itself is still atomic
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# mkstemp makes its files 0600; an output gets the mode any new file of the user gets.
_FILE_MODE = 0o666 & ~_umask()


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Call write(tmp) on a temporary name beside `path`, fsync, then os.replace onto `path`.

    On any failure the temporary file is removed and `path` keeps its previous content (or stays
    absent); a full or read-only disk raises `OutputWriteError` naming the folder.
    """
    path = check_path(path)
    tmp: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{path.stem}.", suffix=path.suffix, dir=path.parent)
        os.close(fd)
        tmp = Path(name)
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
        tmp = None
        _fsync_dir(path.parent)
    except OSError as exc:
        # numpy reports a short write without an errno ("3072 requested and 3040 written")
        err = disk_error(exc, path.parent) or _full_disk(path.parent)
        if err is not None:
            raise err from exc
        raise
    except Exception as exc:
        # Some writers wrap the OSError (torch.save raises RuntimeError "file write failed"):
        # ask the file system whether it is full before passing the error on.
        err = _full_disk(path.parent)
        if err is not None:
            raise err from exc
        raise
    finally:
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically (UTF-8)."""
    atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write a binary file atomically."""
    atomic_write(path, lambda p: p.write_bytes(data))


def copy_file(src: str | Path, dst: str | Path) -> None:
    """Copy `src`'s bytes to `dst` atomically (`dst` follows no link; `src` is only read)."""
    atomic_write(dst, lambda p: shutil.copyfile(src, p))
