"""coin-cl's kernel cache (coin_cl.engine.kernel_cache): builds land in its own folder and are
retrieved from it; a pyopencl lock file left by a build killed mid-way is removed instead of making
every later build wait for it; COIN_CL_KERNEL_CACHE=0 builds without a disk cache."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from coin_cl.engine import kernel_cache

SOURCE = "__kernel void twice(__global float *x) { x[get_global_id(0)] *= 2.0f; }"


@pytest.fixture
def context():
    from coin_cl.engine import get_runtime

    return get_runtime().context


def _runs(context, program) -> bool:
    import pyopencl as cl

    queue = cl.CommandQueue(context)
    x = np.arange(8, dtype=np.float32)
    buf = cl.Buffer(context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
    program.twice(queue, (8,), None, buf)
    cl.enqueue_copy(queue, x, buf)
    queue.finish()
    return bool(np.array_equal(x, 2 * np.arange(8, dtype=np.float32)))


def test_a_build_is_cached_in_coin_cls_folder_and_retrieved(context, tmp_path, monkeypatch):
    from pyopencl.characterize import has_src_build_cache

    if has_src_build_cache(context.devices[0]):
        pytest.skip("this driver caches builds itself; pyopencl writes no entry")
    monkeypatch.setenv("COIN_CL_KERNEL_CACHE", str(tmp_path / "kernels"))
    assert kernel_cache.cache_dir() == tmp_path / "kernels"
    first = kernel_cache.build(context, SOURCE, ["-DUNUSED=1"])
    assert _runs(context, first)
    entries = sorted((tmp_path / "kernels").iterdir())
    assert entries  # pyopencl wrote its entry there
    again = kernel_cache.build(context, SOURCE, ["-DUNUSED=1"])
    assert _runs(context, again)
    assert sorted((tmp_path / "kernels").iterdir()) == entries  # retrieved: nothing new written
    kernel_cache.build(context, SOURCE, ["-DUNUSED=2"])  # another variant: a new entry
    assert len(list((tmp_path / "kernels").iterdir())) == len(entries) + 1
    assert not (tmp_path / "kernels" / kernel_cache.PYOPENCL_LOCK).exists()


def test_a_lock_left_by_a_killed_build_is_removed(context, tmp_path, monkeypatch, caplog):
    folder = tmp_path / "kernels"
    monkeypatch.setenv("COIN_CL_KERNEL_CACHE", str(folder))
    kernel_cache.build(context, SOURCE)  # an entry to retrieve: pyopencl takes its lock to read it
    (folder / kernel_cache.PYOPENCL_LOCK).touch()  # what a process killed inside pyopencl leaves
    with caplog.at_level("WARNING", logger="coin_cl.engine.kernel_cache"):
        prg = kernel_cache.build(context, SOURCE)
    assert _runs(context, prg)
    assert not (folder / kernel_cache.PYOPENCL_LOCK).exists()
    assert "killed" in caplog.text


def test_a_file_named_lock_that_is_not_pyopencls_is_left_alone(tmp_path):
    folder = tmp_path / "kernels"
    folder.mkdir()
    (folder / kernel_cache.PYOPENCL_LOCK).write_text("a user's notes")
    with kernel_cache.exclusive(folder):
        pass
    assert (folder / kernel_cache.PYOPENCL_LOCK).read_text() == "a user's notes"


@pytest.mark.skipif(sys.platform == "win32", reason="fcntl locks: POSIX")
def test_a_build_killed_while_it_holds_the_lock_releases_it(tmp_path):
    """A process killed while it holds coin-cl's build lock does not block the next one."""
    folder = tmp_path / "kernels"
    holder = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {str(Path(kernel_cache.__file__).parents[2])!r})
        from pathlib import Path
        from coin_cl.engine.kernel_cache import exclusive, PYOPENCL_LOCK
        folder = Path({str(folder)!r})
        with exclusive(folder):
            (folder / PYOPENCL_LOCK).touch()
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", holder], timeout=60)
    assert proc.returncode != 0 and (folder / kernel_cache.PYOPENCL_LOCK).exists()
    with kernel_cache.exclusive(folder):  # returns at once: the kernel released the dead holder's lock
        assert not (folder / kernel_cache.PYOPENCL_LOCK).exists()


def test_the_disk_cache_can_be_turned_off(context, tmp_path, monkeypatch):
    monkeypatch.setenv("COIN_CL_KERNEL_CACHE", "0")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert kernel_cache.cache_dir() is None
    assert _runs(context, kernel_cache.build(context, SOURCE))
    assert not (tmp_path / "coin-cl" / "kernels").exists()
