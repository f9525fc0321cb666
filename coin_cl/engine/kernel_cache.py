"""Compiled kernels cached on disk, safe against runs killed while they build.

pyopencl keeps compiled programs in a cache folder guarded by a lock *file* (created exclusively,
removed when done). A process killed inside that window (`kill -9`, a machine's OOM killer, a fault
test) leaves the file behind, and every later build of every process then waits 60 s for it before
building without the cache: a run that builds a dozen kernels stalls for many minutes, silently.

coin-cl therefore keeps its own cache folder (`cache_dir`) and builds under an advisory lock
(`fcntl.flock` on a file beside the folder) that the operating system releases when its holder
dies. Every coin-cl build takes it first, so while one holds it no other coin-cl process is inside
pyopencl's window, and a pyopencl lock file found then was left by a killed process: it is removed
(logged). The lock is held for the whole build, so two coin-cl processes compiling at once take
turns (a cache hit takes milliseconds; a cold build, one per kernel variant, seconds). Where `fcntl`
does not exist (Windows) builds go through pyopencl's own locking.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# pyopencl's lock file inside a cache folder (pyopencl/cache.py, CacheLockManager).
PYOPENCL_LOCK = "lock"


def cache_dir() -> Path | None:
    """The folder of coin-cl's compiled kernels: $COIN_CL_KERNEL_CACHE ("0": no disk cache, None),
    else `coin-cl/kernels` in the user's cache folder ($XDG_CACHE_HOME or ~/.cache)."""
    env = os.environ.get("COIN_CL_KERNEL_CACHE")
    if env == "0":
        return None
    if env:
        return Path(env)
    from coin_cl.engine.icd import cache_root

    return cache_root() / "kernels"


@contextlib.contextmanager
def exclusive(folder: Path) -> Iterator[None]:
    """Hold coin-cl's build lock of `folder` (module doc), removing a pyopencl lock file that a
    killed build left in it."""
    try:
        import fcntl
    except ImportError:  # Windows: pyopencl's own locking alone
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f"{folder.name}.flock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        try:
            stale = folder / PYOPENCL_LOCK
            # pyopencl's lock is an empty regular file; anything else by that name is not ours to remove
            if stale.is_file() and not stale.is_symlink() and stale.stat().st_size == 0:
                log.warning(
                    "removing %s: a kernel build killed while it held pyopencl's cache lock left it", stale
                )
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(held, fcntl.LOCK_UN)


def build(context: Any, source: str, options: Sequence[str] = ()) -> Any:
    """`pyopencl.Program(context, source)` built with `options`, through coin-cl's disk cache."""
    import pyopencl as cl

    program = cl.Program(context, source)
    folder = cache_dir()
    if folder is None:
        return program.build(options=list(options), cache_dir=False)
    with exclusive(folder):
        return program.build(options=list(options), cache_dir=str(folder))
