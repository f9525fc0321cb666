"""Run a command with Oclgrind (a strict OpenCL 1.2 simulator) as the coin-cl device.

    python -m coin_cl.oclgrind python -m pytest -q -m kernel tests/test_ops.py tests/test_rendering.py

Oclgrind reports out-of-bounds accesses, data races and API misuse; the kernel tests shrink to
sizes it can simulate (COIN_CL_SMALL=1). Its reports go to log files, not to the command's stderr,
where a test runner capturing output would hide them from a passing test: each process writes its
own file (`process_log`; a test session calls it before any OpenCL call), and when the command ends
this prints every report and exits non-zero if any names a kernel error (`KERNEL_ERRORS`), whatever
the command's own exit status. Needs Debian's `oclgrind` package (apt install oclgrind).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

CANDIDATES = [
    "/usr/lib/oclgrind/liboclgrind-rt-icd.so",
    "/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so",
    "/usr/local/lib/liboclgrind-rt-icd.so",
]
# The folder each process under the wrapper writes its Oclgrind log into.
LOG_DIR_ENV = "COIN_CL_OCLGRIND_LOGS"
# What in a log is a kernel error (the API checks' notes about queries the device does not answer,
# which pyopencl makes while probing, are printed but not counted).
KERNEL_ERRORS = re.compile(r"Invalid (read|write)|data race|out-of-bounds|Uninitialized value|OCLGRIND FATAL")


def find_icd_library() -> Path:
    env = os.environ.get("OCLGRIND_ICD_LIB")
    for c in [env] if env else CANDIDATES:
        if c and Path(c).is_file():
            return Path(c)
    raise FileNotFoundError(
        "liboclgrind-rt-icd.so not found: install Oclgrind (`apt install oclgrind`) or point "
        "OCLGRIND_ICD_LIB at the library"
    )


def oclgrind_env(log_dir: Path) -> dict[str, str]:
    """Environment that makes coin-cl run on Oclgrind with its checks on, logging into `log_dir`."""
    icd_dir = Path(tempfile.mkdtemp(prefix="coin-cl-oclgrind-"))
    (icd_dir / "oclgrind.icd").write_text(f"{find_icd_library()}\n")
    env = dict(os.environ)
    env.update(
        OCL_ICD_VENDORS=str(icd_dir),
        COIN_CL_DEVICE="oclgrind",
        COIN_CL_SMALL="1",
        OCLGRIND_CHECK_API="1",
        OCLGRIND_DATA_RACES="1",
        OCLGRIND_LOG=str(log_dir / "main.log"),
        **{LOG_DIR_ENV: str(log_dir)},
    )
    return env


def process_log() -> None:
    """Under the wrapper, point this process's Oclgrind log at a file of its own (Oclgrind opens
    OCLGRIND_LOG for writing, so processes sharing one, such as a test run's workers, would
    overwrite each other's reports). Call it before the process's first OpenCL call; elsewhere it
    does nothing."""
    folder = os.environ.get(LOG_DIR_ENV)
    if folder:
        os.environ["OCLGRIND_LOG"] = str(Path(folder) / f"{os.getpid()}.log")


def report(log_dir: Path) -> int:
    """Print every non-empty log in `log_dir` to stderr; the number of kernel errors among them."""
    errors = 0
    for log in sorted(Path(log_dir).glob("*.log")):
        text = log.read_text(errors="replace")
        if text.strip():
            print(f"== Oclgrind log of process {log.stem}:\n{text}", file=sys.stderr)
            errors += len(KERNEL_ERRORS.findall(text))
    return errors


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    log_dir = Path(tempfile.mkdtemp(prefix="coin-cl-oclgrind-logs-"))
    rc = subprocess.call(argv, env=oclgrind_env(log_dir))
    errors = report(log_dir)
    if errors:
        print(f"Oclgrind reported {errors} kernel error(s) (above)", file=sys.stderr)
        return rc or 1
    return rc


if __name__ == "__main__":
    sys.exit(main())
