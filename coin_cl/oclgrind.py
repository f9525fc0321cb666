"""Run a command with Oclgrind (a strict OpenCL 1.2 simulator) as the coin-cl device.

    python -m coin_cl.oclgrind python -m pytest tests/test_ops.py tests/test_rendering.py

Oclgrind reports out-of-bounds accesses, data races and API misuse; the kernel tests shrink to
sizes it can simulate (COIN_CL_SMALL=1). Needs Debian's `oclgrind` package (apt install oclgrind).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

CANDIDATES = [
    "/usr/lib/oclgrind/liboclgrind-rt-icd.so",
    "/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so",
    "/usr/local/lib/liboclgrind-rt-icd.so",
]


def find_icd_library() -> Path:
    env = os.environ.get("OCLGRIND_ICD_LIB")
    for c in [env] if env else CANDIDATES:
        if c and Path(c).is_file():
            return Path(c)
    raise FileNotFoundError(
        "liboclgrind-rt-icd.so not found: install Oclgrind (`apt install oclgrind`) or point "
        "OCLGRIND_ICD_LIB at the library"
    )


def oclgrind_env() -> dict[str, str]:
    """Environment that makes coin-cl run on Oclgrind with its checks on."""
    icd_dir = Path(tempfile.mkdtemp(prefix="coin-cl-oclgrind-"))
    (icd_dir / "oclgrind.icd").write_text(f"{find_icd_library()}\n")
    env = dict(os.environ)
    env.update(
        OCL_ICD_VENDORS=str(icd_dir),
        COIN_CL_DEVICE="oclgrind",
        COIN_CL_SMALL="1",
        OCLGRIND_CHECK_API="1",
        OCLGRIND_DATA_RACES="1",
    )
    return env


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    env = oclgrind_env()
    os.execvpe(argv[0], argv, env)
    return 0  # unreachable


if __name__ == "__main__":
    sys.exit(main())
