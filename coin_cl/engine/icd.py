"""OpenCL platform registration: make every implementation installed in this environment visible.

The OpenCL ICD loader finds implementations through `.icd` files in one folder: `$OCL_ICD_VENDORS`
when it is set, else `/etc/OpenCL/vendors`. pip-installed implementations do not register there:
Intel's CPU runtime (`intel-opencl-rt`) ships an ICD file that names a placeholder build path, so it
stays invisible. PoCL needs nothing: the pyopencl wheel's bundled loader always adds its own PoCL.

`register_platforms()` therefore writes one folder of `.icd` files naming
  - every implementation found in the Python environment (Intel's `libintelocl.so`),
  - every entry of the system folder `/etc/OpenCL/vendors` (GPU drivers; setting the variable
    replaces that folder, so its entries must be carried over),
  - every entry of the folder or file the user already named in `OCL_ICD_VENDORS`,
and points `OCL_ICD_VENDORS` at it. The folder is content-addressed in a per-user cache
(`$XDG_CACHE_HOME/coin-cl/icd-<hash>`), written once through a temporary name and a rename, so
concurrent processes never see half a folder and a current folder is not rewritten. A read-only
home falls back to a temporary folder (logged). `COIN_CL_NO_ICD=1` switches all of this off.

It must run before pyopencl first lists platforms (the loader reads the folder once per process):
`coin_cl.engine.devices` calls it on import.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import sys
import tempfile
from importlib import metadata
from pathlib import Path

log = logging.getLogger(__name__)

SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")
# Libraries of OpenCL implementations that pip installs without registering them, by distribution.
ENV_IMPLEMENTATIONS = {"intel-opencl-rt": ("libintelocl.so", "intelocl64.dll")}
_MARKER = "COIN_CL_ICD_DIR"  # the folder this process registered, so a second call is a no-op


def environment_libraries() -> dict[str, Path]:
    """{icd file name: library path} of the OpenCL implementations installed in this environment."""
    found: dict[str, Path] = {}
    for dist, names in ENV_IMPLEMENTATIONS.items():
        try:
            files = metadata.distribution(dist).files or []
        except metadata.PackageNotFoundError:
            continue
        for f in files:
            if Path(str(f)).name in names:
                path = Path(str(f.locate())).resolve()
                if path.is_file():
                    found[f"{dist}.icd"] = path
                    break
        else:
            # Some installers put the library in the environment's lib/ without listing it.
            for name in names:
                path = Path(sys.prefix) / "lib" / name
                if path.is_file():
                    found[f"{dist}.icd"] = path.resolve()
                    break
    return found


def _icd_entries(folder_or_file: Path) -> dict[str, str]:
    """{file name: library line} of the .icd files in a folder (or of one .icd file)."""
    if folder_or_file.is_file():
        files = [folder_or_file]
    elif folder_or_file.is_dir():
        files = sorted(folder_or_file.glob("*.icd"))
    else:
        return {}
    out = {}
    for f in files:
        try:
            line = f.read_text().strip()
        except OSError as exc:
            log.warning("OpenCL: cannot read %s (%s); skipped", f, exc)
            continue
        if line:
            out[f.name] = line
    return out


def wanted_entries(user: str | None, system: Path | None = None) -> dict[str, str]:
    """The .icd files the registration folder must hold: the system's, the user's, the environment's.

    The same library named twice (say, Intel's runtime installed system-wide and in the venv) is
    kept once, so each platform is listed once.
    """
    entries: dict[str, str] = {}
    sources = [_icd_entries(SYSTEM_VENDORS if system is None else system)]
    for part in (user or "").split(os.pathsep):
        if part:
            sources.append(_icd_entries(Path(part)))
    sources.append({name: str(path) for name, path in environment_libraries().items()})
    seen: set[str] = set()
    for src in sources:
        for name, line in src.items():
            key = os.path.realpath(line) if os.path.isabs(line) else line
            if key in seen:
                continue
            seen.add(key)
            while name in entries:  # two sources may both call their file intel.icd
                name = "_" + name
            entries[name] = line
    return entries


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "coin-cl"


def write_folder(entries: dict[str, str], root: Path) -> Path:
    """The content-addressed folder holding `entries` under `root`; written only when absent."""
    digest = hashlib.sha256(repr(sorted(entries.items())).encode()).hexdigest()[:16]
    final = root / f"icd-{digest}"
    if final.is_dir() and _icd_entries(final) == entries:
        return final
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".icd-tmp-", dir=root))
    try:
        for name, line in entries.items():
            (tmp / name).write_text(line + "\n")
        try:
            os.rename(tmp, final)
        except OSError:
            # Another process won the race (or a stale, different folder is in the way): theirs
            # has the same content by construction of the name, unless stale.
            if _icd_entries(final) != entries:
                shutil.rmtree(final, ignore_errors=True)
                os.rename(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def register_platforms() -> Path | None:
    """Point OCL_ICD_VENDORS at a folder naming every OpenCL implementation available here.

    Returns the folder, or None when nothing needs registering (no implementation in the
    environment beyond what the loader finds by itself) or when COIN_CL_NO_ICD=1.
    """
    if os.environ.get("COIN_CL_NO_ICD", "") not in ("", "0"):
        return None
    current = os.environ.get("OCL_ICD_VENDORS")
    if current and current == os.environ.get(_MARKER):
        return Path(current)
    if not environment_libraries():
        return None  # nothing pip-installed to add: leave the loader's own search alone
    entries = wanted_entries(current)
    try:
        folder = write_folder(entries, cache_root())
    except OSError as exc:
        folder = write_folder(entries, Path(tempfile.mkdtemp(prefix="coin-cl-icd-")))
        log.info("OpenCL: %s not writable (%s); ICD folder in %s", cache_root(), exc, folder)
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    os.environ[_MARKER] = str(folder)
    log.debug("OpenCL: OCL_ICD_VENDORS=%s (%s)", folder, ", ".join(sorted(entries.values())))
    return folder
