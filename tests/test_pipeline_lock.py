"""One run per output folder: the lock names its holder, refuses a second run, takes over a dead one's."""

import json
import logging
import os
import signal
import subprocess
import sys

import pytest

from coin_cl.pipeline.lock import LOCK_NAME, FolderLockedError, acquire, folder_lock
from coin_cl.pipeline.runner import Stage, run_stages

HOLD = """
import sys, time
from coin_cl.pipeline.lock import acquire
lk = acquire(sys.argv[1])
print("held", flush=True)
time.sleep(120)
"""


def test_lock_records_holder_and_is_released(tmp_path):
    with folder_lock(tmp_path / "out") as lk:
        info = json.loads((tmp_path / "out" / LOCK_NAME).read_text())
        assert info["pid"] == os.getpid() and info["host"] and info["started"]
        assert lk.info == info
    assert not (tmp_path / "out" / LOCK_NAME).exists()
    acquire(tmp_path / "out").release()  # free again


def test_second_holder_is_refused_naming_the_first(tmp_path):
    with folder_lock(tmp_path):
        with pytest.raises(FolderLockedError, match=rf"in use by another coin-cl run: process {os.getpid()}"):
            acquire(tmp_path)
    assert not (tmp_path / LOCK_NAME).exists()


def test_stale_lock_of_a_dead_process_is_taken_over_with_a_log_line(tmp_path, caplog):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": dead.pid, "host": "h", "started": "then"}))
    with caplog.at_level(logging.WARNING, "coin_cl.pipeline.lock"):
        lk = acquire(tmp_path)
    assert f"process {dead.pid} on host h" in caplog.text and "stale" in caplog.text
    assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    lk.release()


def test_two_real_processes_then_sigkill_frees_the_folder(tmp_path, caplog):
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    child = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, env=env, text=True
    )
    try:
        assert child.stdout.readline().strip() == "held"
        with pytest.raises(FolderLockedError, match=rf"process {child.pid} on host"):
            acquire(tmp_path)
        child.send_signal(signal.SIGKILL)
        child.wait()
        assert (tmp_path / LOCK_NAME).exists()  # a killed run leaves its lock file behind...
        with caplog.at_level(logging.WARNING, "coin_cl.pipeline.lock"):
            lk = acquire(tmp_path)  # ...which the next run takes over
        assert f"process {child.pid}" in caplog.text
        lk.release()
    finally:
        child.kill()
        child.wait()


def test_run_stages_holds_the_lock_and_releases_it_on_an_exception(tmp_path):
    seen = []

    def check(ctx):
        seen.append((tmp_path / LOCK_NAME).is_file())
        with pytest.raises(FolderLockedError):
            acquire(tmp_path)  # a second holder (another run: nested run_stages in one process share it)
        return {}

    def boom(ctx):
        raise RuntimeError("stage failed")

    run_stages(tmp_path, [Stage("1_a", check)])
    assert seen == [True] and not (tmp_path / LOCK_NAME).exists()
    with pytest.raises(RuntimeError, match="stage failed"):
        run_stages(tmp_path, [Stage("1_b", boom)])
    assert not (tmp_path / LOCK_NAME).exists()
    assert run_stages(tmp_path, [Stage("1_c", lambda c: {})])["1_c"]["status"] == "ran"


def test_nested_folder_locks_share_the_commands_lock(tmp_path):
    from coin_cl.pipeline.lock import command_lock

    with command_lock(tmp_path) as outer:
        with folder_lock(tmp_path) as inner:  # the pipeline inside a command: not refused
            assert inner is outer
        assert (tmp_path / LOCK_NAME).exists()  # the inner block did not release it
        with pytest.raises(FolderLockedError):
            with command_lock(tmp_path):  # a second command in this process is refused
                pass
    assert not (tmp_path / LOCK_NAME).exists()


@pytest.mark.parametrize("where", ["mkdir", "open"])
def test_a_read_only_output_folder_is_one_line_naming_it(tmp_path, monkeypatch, where):
    """The lock is a command's first write in its folder: a read-only disk there is the one-line
    OutputWriteError naming the folder, not Python's "[Errno 30] Read-only file system"."""
    import errno
    from pathlib import Path

    from coin_cl.atomic import OutputWriteError

    def refuse(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system", str(a[0]))

    if where == "mkdir":
        monkeypatch.setattr(Path, "mkdir", refuse)
    else:
        (tmp_path / "out").mkdir()
        monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(OutputWriteError) as exc:
        acquire(tmp_path / "out")
    assert str(exc.value) == (
        f"cannot write in {tmp_path / 'out'}: the file system is read-only; make it writable or "
        "choose another output folder"
    )
