"""The Oclgrind wrapper (`python -m coin_cl.oclgrind CMD`): a kernel error Oclgrind reports fails
the command even when the test that ran the kernel passes and its output was captured."""

import subprocess
import sys
import textwrap

import pytest

from coin_cl import oclgrind


def test_report_counts_kernel_errors_and_prints_every_log(tmp_path, capsys):
    (tmp_path / "1.log").write_text("Invalid write of size 4 at global memory address 0x10\n\tKernel: k\n")
    (tmp_path / "2.log").write_text("Read-write data race at global memory address 0x20\n")
    (tmp_path / "3.log").write_text("")  # a process that reported nothing
    (tmp_path / "4.log").write_text("Oclgrind - OpenCL runtime error detected\n\tFunction: clGetDeviceInfo\n")
    assert oclgrind.report(tmp_path) == 2
    err = capsys.readouterr().err
    assert "process 1" in err and "process 4" in err and "process 3" not in err


def test_each_process_logs_to_a_file_of_its_own(tmp_path, monkeypatch):
    monkeypatch.delenv(oclgrind.LOG_DIR_ENV, raising=False)
    monkeypatch.setenv("OCLGRIND_LOG", "/x/main.log")
    oclgrind.process_log()  # not under the wrapper: nothing changes
    assert oclgrind.os.environ["OCLGRIND_LOG"] == "/x/main.log"
    monkeypatch.setenv(oclgrind.LOG_DIR_ENV, str(tmp_path))
    oclgrind.process_log()
    assert oclgrind.os.environ["OCLGRIND_LOG"] == str(tmp_path / f"{oclgrind.os.getpid()}.log")


def test_an_out_of_bounds_write_in_a_passing_test_fails_the_command(tmp_path):
    try:
        oclgrind.find_icd_library()
    except FileNotFoundError as e:
        pytest.skip(str(e))
    (tmp_path / "conftest.py").write_text("from coin_cl.oclgrind import process_log\nprocess_log()\n")
    (tmp_path / "test_oob.py").write_text(textwrap.dedent("""
        import pyopencl as cl

        def test_writes_past_the_end():
            ctx = cl.create_some_context(interactive=False)
            q = cl.CommandQueue(ctx)
            src = "__kernel void k(__global float* a) { a[get_global_id(0) + 4] = 1.0f; }"
            k = cl.Program(ctx, src).build().k
            buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 16)
            k(q, (4,), None, buf)
            q.finish()
    """))  # fmt: skip
    cmd = [sys.executable, "-m", "coin_cl.oclgrind", sys.executable, "-m", "pytest", "-q", "-p",
           "no:cacheprovider", "-n", "2", str(tmp_path)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert "1 passed" in proc.stdout  # the test itself passes: its kernel's errors are Oclgrind's
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "Invalid write" in proc.stderr and "kernel error(s)" in proc.stderr
