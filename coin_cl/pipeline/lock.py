"""One run per output folder: a lock file naming its holder (process id, host, start time).

A CoIn run writes a dozen stage folders under `OUT/`; two runs on one folder would resume each
other's half-written stages. `folder_lock(OUT)` creates `OUT/.coin-cl.lock` with O_CREAT|O_EXCL
(atomic: of two runs exactly one creates it) and holds an advisory `flock` on it for its lifetime.
The kernel drops a `flock` when its process dies, however it dies (SIGKILL included), so:

- the lock exists and its flock is held: a live run holds it; `FolderLockedError` names it (pid,
  host, start time, command) and says what to do;
- the lock exists but nobody holds its flock: the run that wrote it is gone (killed, crashed);
  the lock is taken over, with a log line naming the dead holder.

The process id in the file is for people (and for the message); the flock decides, so a reused
process id can never make a stale lock look live. On a file system without `flock` (some network
mounts) the process id decides instead: a lock of a live process on this host, or of another
host, is refused (the message says to delete the file if that run is gone).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coin_cl.atomic import disk_error

log = logging.getLogger(__name__)

LOCK_NAME = ".coin-cl.lock"


class FolderLockedError(RuntimeError):
    """Another live run holds the output folder's lock."""


@dataclass
class FolderLock:
    """A held lock: `path` of the lock file and the open descriptor carrying its flock."""

    path: Path
    fd: int
    info: dict[str, Any]

    def release(self) -> None:
        """Remove the lock file and drop the flock (idempotent). Unlink first, while still holding
        the flock, so no other run can lock this file's inode in between."""
        if self.fd < 0:
            return
        try:
            st = os.fstat(self.fd)
            cur = os.stat(self.path)
            if (cur.st_dev, cur.st_ino) == (st.st_dev, st.st_ino):
                self.path.unlink()
        except FileNotFoundError:
            pass
        finally:
            os.close(self.fd)
            self.fd = -1


def _holder_info() -> dict[str, Any]:
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": " ".join(sys.argv)[:300],
    }


def _describe(info: dict[str, Any] | None) -> str:
    if not info:
        return "an unknown process (the lock file is empty or unreadable)"
    return (
        f"process {info.get('pid')} on host {info.get('host')} since {info.get('started')} "
        f"({info.get('command') or 'no command recorded'})"
    )


def _read(fd: int) -> dict[str, Any] | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return json.loads(os.read(fd, 1 << 16).decode() or "null")
    except (OSError, ValueError):
        return None


def _write(fd: int, info: dict[str, Any]) -> None:
    os.lseek(fd, 0, os.SEEK_SET)
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps(info).encode())
    os.fsync(fd)


def _try_flock(fd: int) -> bool | None:
    """True: this process now holds the flock; False: another holds it; None: no flock here."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as exc:
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        log.debug("flock unavailable on %s: %s", fd, exc)  # ENOLCK / EOPNOTSUPP (some NFS)
        return None


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # alive, another user's
    return True


def _raise_disk_error(exc: OSError, folder: Path) -> None:
    """Re-raise `exc`, as the one-line `OutputWriteError` naming `folder` when it is a read-only or
    full disk or a missing permission (the lock is a command's first write in its folder)."""
    err = disk_error(exc, folder)
    if err is None:
        raise exc
    raise err from exc


def acquire(folder: str | Path) -> FolderLock:
    """Take `folder`'s lock (creating the folder); raises `FolderLockedError` naming the holder
    when a live run has it, takes over (with a log line) a lock whose holder is gone."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _raise_disk_error(exc, folder)
    path = folder / LOCK_NAME
    me = _holder_info()
    for _ in range(20):  # retries only when a holder releases between our steps
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            pass
        except OSError as exc:
            _raise_disk_error(exc, folder)
        else:
            if _try_flock(fd) is False:  # another run took our brand-new file over in between
                os.close(fd)
                continue
            _write(fd, me)
            return FolderLock(path, fd, me)
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            continue  # released meanwhile: try creating again
        got = _try_flock(fd)
        if got is False:
            holder = _read(fd)
            os.close(fd)
            raise FolderLockedError(
                f"{folder} is in use by another coin-cl run: {_describe(holder)}. Wait for it to "
                f"finish or stop it, or pick another output folder (lock file {path})"
            )
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # we locked a file its holder had just removed
            os.close(fd)
            continue
        old = _read(fd)
        if got is None and old and (old.get("host") != me["host"] or _pid_alive(int(old.get("pid", -1)))):
            os.close(fd)
            raise FolderLockedError(
                f"{folder} has the lock of {_describe(old)} and this file system cannot tell whether "
                f"that run still writes there (no flock): wait for it, or delete {path} if it is gone"
            )
        log.warning("taking over the stale lock %s of %s: that run is gone", path, _describe(old))
        _write(fd, me)
        return FolderLock(path, fd, me)
    raise FolderLockedError(f"could not take the lock {path}: it keeps changing hands; retry")


# Locks this process holds through `folder_lock`, by absolute folder: a command that locks its
# --out before planning calls the pipeline, which locks the same folder again (nested, not refused).
_HELD: dict[str, FolderLock] = {}


@contextmanager
def folder_lock(folder: str | Path) -> Iterator[FolderLock]:
    """`with folder_lock(OUT):` hold OUT's lock for the block, released on exceptions too. Nested
    blocks of one process on one folder share the outer block's lock."""
    key = os.path.abspath(folder)
    held = _HELD.get(key)
    if held is not None and held.fd >= 0:
        yield held
        return
    lk = acquire(folder)
    _HELD[key] = lk
    try:
        yield lk
    finally:
        _HELD.pop(key, None)
        lk.release()


@contextmanager
def command_lock(folder: str | Path) -> Iterator[FolderLock]:
    """A command's own lock on its output folder: refused when anyone holds it, this process
    included; `folder_lock` blocks inside it share it."""
    key = os.path.abspath(folder)
    lk = acquire(folder)
    _HELD[key] = lk
    try:
        yield lk
    finally:
        _HELD.pop(key, None)
        lk.release()
