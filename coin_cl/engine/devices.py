"""OpenCL devices: which are visible, which build and run kernels, and which one to use.

Device choice (docs/DESIGN.md section 3, the runtime layer): the `device` argument or `COIN_CL_DEVICE`
(a case-insensitive substring of "platform / device", e.g. "oclgrind", "nvidia", "intel",
"pthread"); a requested device that cannot build kernels is an error. Otherwise devices are tried
in `default_rank` order (a GPU, then Intel's CPU runtime, then PoCL), each probed by building and
running a tiny kernel; one that fails is skipped with a log line carrying the compiler's message.
A GPU that cannot run the kernels (no working float atomic add, too little local memory for the
GPU rasterizer, `coin_cl.engine.limits`) ranks behind the CPU.

Importing this module readies the process for OpenCL: platforms installed by pip are made visible
first by `coin_cl.icd.register_platforms`, and pyopencl's kernel cache gets a working default.
`kernel_dir` (where the OpenCL C sources are) lives here too: the probes build the kernels' own
common.h, and `coin_cl.engine.runtime` builds its programs from the same folder.
"""

from __future__ import annotations

import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

from coin_cl.engine import kernel_cache
from coin_cl.engine.errors import NoDeviceError
from coin_cl.engine.icd import register_platforms
from coin_cl.engine.limits import min_raster_gpu_local_bytes

log = logging.getLogger(__name__)

# Before pyopencl first lists platforms: the ICD loader reads its vendor folder once per process.
register_platforms()

# pyopencl (2026.1, cache.py) reads os.environ["PYOPENCL_CACHE_FAILURE_FATAL"] without a default
# when its on-disk kernel cache fails (for instance two processes writing one entry at once), so a
# cache hiccup becomes KeyError('PYOPENCL_CACHE_FAILURE_FATAL') and the device looks broken (seen
# here: "no OpenCL device can build kernels" in one of five concurrent runs). Empty = its intended
# default: warn and build from source.
os.environ.setdefault("PYOPENCL_CACHE_FAILURE_FATAL", "")

INSTALL_HINT = (
    "install an OpenCL driver: `pip install pocl-binary-distribution` gives a CPU device "
    "(GPU vendors ship their own); `coin-cl doctor` lists what is visible"
)
# What to do when devices exist but none builds the kernels (PoCL 3.0's LLVM 14 on newer CPUs).
NO_BUILD_HINT = (
    "On CPUs newer than PoCL's LLVM knows, `pip install intel-opencl-rt intel-cmplr-lib-rt` gives a "
    "working CPU device; " + INSTALL_HINT
)


def kernel_dir() -> Path:
    """Folder holding the OpenCL C sources: $COIN_CL_KERNEL_DIR (for kernel development), else the
    package data (./kernels in a checkout)."""
    env = os.environ.get("COIN_CL_KERNEL_DIR")
    if env:
        if not (Path(env) / "common.h").is_file():
            raise FileNotFoundError(f"COIN_CL_KERNEL_DIR={env} holds no common.h")
        return Path(env)
    # kernels/ holds no __init__.py: as a regular package on sys.path (a checkout's root is, under
    # `python -m pytest`) it would shadow the top-level `kernels` distribution transformers imports.
    # Installed, its files sit in coin_cl/kernels; in a checkout or an editable install, in ./kernels.
    here = Path(__file__).resolve().parents[1]
    for p in (here / "kernels", here.parent / "kernels"):
        if (p / "common.h").is_file():
            return p
    raise FileNotFoundError(f"OpenCL kernel sources not found (looked in {here / 'kernels'} and "
                            f"{here.parent / 'kernels'}); reinstall coin-cl")  # fmt: skip


def list_devices() -> list[tuple[str, str, str]]:
    """(platform name, device name, version) of every visible OpenCL device."""
    return [(p.name, d.name, d.version) for p, d in all_devices()]


def all_devices() -> list:
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return []
    out = []
    for p in platforms:
        try:
            out += [(p, d) for d in p.get_devices()]
        except cl.Error:
            continue
    return out


def device_label(device) -> str:
    return f"{device.platform.name} / {device.name}"


# A kernel that every working compiler builds: a build or a wrong result marks a device unusable
# (PoCL 3.0's LLVM 14, for one, refuses every build on CPUs newer than it knows).
_PROBE_SOURCE = """
__kernel void probe(__global float *x)
{
    int i = get_global_id(0);
    x[i] = sqrt((float)i) * 2.0f + 1.0f;
}
"""
_PROBE_ATOMICS = """
__kernel void probe(__global float *x)
{
    atomic_fetch_add_explicit((volatile __global atomic_float *)x, 0.5f, memory_order_relaxed);
}
"""
FLOAT_ATOMICS_OPTIONS = ("-cl-std=CL3.0",)


@dataclass(frozen=True)
class Probe:
    """Whether a device builds and runs the probe kernel; `message` says why not."""

    ok: bool
    message: str
    seconds: float


_PROBES: dict[tuple[str, str, str], Probe] = {}


def _probe_key(device) -> tuple[str, str, str]:
    return (device.platform.name, device.name, device.version)


def probe_device(device) -> Probe:
    """Build and run a tiny kernel on `device` (once per process); never raises."""
    import time

    import numpy as np
    import pyopencl as cl

    key = _probe_key(device)
    if key in _PROBES:
        return _PROBES[key]
    t0 = time.perf_counter()
    try:
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            prg = kernel_cache.build(ctx, _PROBE_SOURCE)
        n = 64
        out = np.full(n, np.nan, np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
        prg.probe(queue, (n,), None, buf)
        cl.enqueue_copy(queue, out, buf)
        queue.finish()
        want = np.sqrt(np.arange(n, dtype=np.float32)) * 2 + 1
        if np.allclose(out, want, rtol=1e-5):
            result = Probe(True, "ok", time.perf_counter() - t0)
        else:
            result = Probe(False, "probe kernel ran but returned wrong values", time.perf_counter() - t0)
    except Exception as exc:  # any failure of a foreign driver marks the device unusable
        msg = " ".join(str(exc).split())
        result = Probe(False, msg[:400], time.perf_counter() - t0)
    _PROBES[key] = result
    return result


def _adds_exactly(device, source: str, options: list[str], what: str) -> bool:
    """Whether `device` builds `source` (a kernel `probe` adding 0.5 to one float from each of its
    256 work-items, all at once) and the float ends at exactly 128; never raises."""
    import numpy as np
    import pyopencl as cl

    try:
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            prg = kernel_cache.build(ctx, source, options)
        out = np.zeros(1, np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=out)
        prg.probe(queue, (256,), None, buf)
        cl.enqueue_copy(queue, out, buf)
        queue.finish()
        return bool(out[0] == 128.0)
    except Exception as exc:
        log.info("%s unusable on %s: %s", what, device_label(device), " ".join(str(exc).split())[:200])
        return False


def probe_float_atomics(device) -> bool:
    """Whether `device` builds and runs a float atomic add (cl_ext_float_atomics, OpenCL C 3.0)."""
    if "cl_ext_float_atomics" not in device.extensions:
        return False
    return _adds_exactly(device, _PROBE_ATOMICS, list(FLOAT_ATOMICS_OPTIONS), "float atomics")


# The compare-and-swap float add every backward falls back to (kernels/common.h), run under
# contention: 256 work-items add 0.5 to one float, which must give exactly 128.
_PROBE_CAS = """
#include "common.h"
__kernel void probe(__global float *x) { atomic_add_float(x, 0.5f); }
"""


def probe_cas_atomics(device) -> bool:
    """Whether `device` builds and runs the compare-and-swap float add of kernels/common.h exactly."""
    return _adds_exactly(device, _PROBE_CAS, [f"-I{kernel_dir()}"], "CAS float add")


_GPU_CHECKS: dict[tuple[str, str, str], str] = {}


def gpu_shortfall(device) -> str:
    """Why a GPU cannot run the kernels as well as the CPU ("" when it can): a float atomic add
    that works (cl_ext_float_atomics, else the compare-and-swap loop) and the local memory the
    narrowest GPU rasterizer needs. Checked once per process and device."""
    key = _probe_key(device)
    if key not in _GPU_CHECKS:
        need = min_raster_gpu_local_bytes()
        have = int(device.local_mem_size)
        if have < need:
            reason = f"local memory {have} B is below the {need} B the GPU rasterizer needs"
        elif not (probe_float_atomics(device) or probe_cas_atomics(device)):
            reason = "neither a float atomic add nor the compare-and-swap fallback builds and adds exactly"
        else:
            reason = ""
        if reason:
            log.warning("OpenCL GPU %s ranks behind the CPU: %s", device_label(device), reason)
        _GPU_CHECKS[key] = reason
    return _GPU_CHECKS[key]


def default_rank(device) -> tuple[int, str]:
    """Order in which devices are tried when none is requested (lower first), and why.

    A GPU first, if it has what the kernels need (`gpu_shortfall`; otherwise behind every CPU);
    then CPU implementations, Intel's runtime ahead of PoCL because it measured faster on the same
    CPU (docs/BENCHMARKS.md, "CPU implementations side by side"); Oclgrind is a simulator and is
    never a default.
    """
    import pyopencl as cl

    pname = device.platform.name.lower()
    if "oclgrind" in pname:
        return (9, "a simulator (use COIN_CL_DEVICE=oclgrind)")
    if device.type & cl.device_type.GPU:
        if probe_device(device).ok:  # a GPU that cannot build at all is skipped by the probe
            short = gpu_shortfall(device)
            if short:
                return (5, f"a GPU ranked behind the CPU: {short}")
        return (0, "a GPU")
    if device.type & cl.device_type.CPU:
        if "intel" in pname:
            return (1, "the fastest CPU implementation measured (Intel's runtime)")
        if "portable computing language" in pname:
            return (2, "a CPU implementation (PoCL)")
        return (3, "a CPU implementation")
    return (4, "another device type")


def working_devices() -> list:
    """Devices that build and run the probe kernel, in default order (simulators left out)."""
    ranked = sorted((d for _, d in all_devices()), key=lambda d: default_rank(d)[0])
    return [d for d in ranked if default_rank(d)[0] < 9 and probe_device(d).ok]


def choose_device(request: str | None):
    """The device named by `request` (a case-insensitive substring of "platform / device"), which
    must build kernels; without one, the first device in `default_rank` order that does. Raises
    `NoDeviceError` saying what is visible or what to install."""
    import pyopencl as cl

    try:
        cl.get_platforms()
    except cl.Error as exc:
        raise NoDeviceError(f"no OpenCL platform found ({exc}); {INSTALL_HINT}") from exc
    devices = [d for _, d in all_devices()]
    if not devices:
        raise NoDeviceError(f"OpenCL platforms exist but list no device; {INSTALL_HINT}")
    if request:
        hits = [d for d in devices if request.lower() in device_label(d).lower()]
        if not hits:
            names = "; ".join(device_label(d) for d in devices)
            raise NoDeviceError(f"no OpenCL device matches {request!r}; visible: {names}")
        probe = probe_device(hits[0])
        if not probe.ok:
            raise NoDeviceError(
                f"OpenCL device {device_label(hits[0])!r} (requested by {request!r}) cannot build or run "
                f"kernels: {probe.message}. Unset COIN_CL_DEVICE to use a working one; `coin-cl doctor` "
                "lists them."
            )
        return hits[0]
    failures = []
    for d in sorted(devices, key=lambda d: default_rank(d)[0]):
        if default_rank(d)[0] >= 9:
            continue
        probe = probe_device(d)
        if probe.ok:
            return d
        log.warning("OpenCL device %s skipped: it cannot build kernels (%s)", device_label(d), probe.message)
        failures.append(f"{device_label(d)}: {probe.message}")
    raise NoDeviceError("no OpenCL device can build kernels (" + "; ".join(failures) + "). " + NO_BUILD_HINT)


def host_unified(device) -> bool:
    """Whether the device shares host memory (CL_DEVICE_HOST_UNIFIED_MEMORY): the CPU
    implementations and integrated GPUs do, discrete GPUs do not."""
    return bool(device.host_unified_memory)
