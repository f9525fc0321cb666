"""OpenCL runtime: device choice, one context and queue, per-variant program cache, shared buffers.

Device choice: the `device` argument or `COIN_CL_DEVICE` (a case-insensitive substring of
"platform / device", e.g. "oclgrind", "nvidia", "pthread"); by default the PoCL CPU device, picked
by name because a machine may list several platforms.

Buffers: on a host-unified-memory device (PoCL on the CPU) a `cl.Buffer` is created over the
torch tensor's own memory (USE_HOST_PTR), so nothing is copied and `queue.finish()` is the
hand-over point. Elsewhere inputs are copied in and outputs copied back, and every byte that
crosses is counted in `Runtime.bytes_transferred`.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import torch

log = logging.getLogger(__name__)

_INSTALL_HINT = (
    "install an OpenCL driver: `pip install pocl-binary-distribution` gives a CPU device "
    "(GPU vendors ship their own); `coin-cl doctor` lists what is visible"
)


class NoDeviceError(RuntimeError):
    """No OpenCL platform/device matches the request."""


def kernel_dir() -> Path:
    """Folder holding the OpenCL C sources: $COIN_CL_KERNEL_DIR (for kernel development), else the
    package data (./kernels in a checkout)."""
    env = os.environ.get("COIN_CL_KERNEL_DIR")
    if env:
        if not (Path(env) / "common.h").is_file():
            raise FileNotFoundError(f"COIN_CL_KERNEL_DIR={env} holds no common.h")
        return Path(env)
    try:
        p = Path(str(resources.files("coin_cl.kernels")))
        if (p / "common.h").is_file():
            return p
    except ModuleNotFoundError:
        pass
    p = Path(__file__).resolve().parent.parent / "kernels"
    if (p / "common.h").is_file():
        return p
    raise FileNotFoundError(f"OpenCL kernel sources not found (looked in {p}); reinstall coin-cl")


def list_devices() -> list[tuple[str, str, str]]:
    """(platform name, device name, version) of every visible OpenCL device."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return []
    out = []
    for p in platforms:
        try:
            for d in p.get_devices():
                out.append((p.name, d.name, d.version))
        except cl.Error:
            continue
    return out


def _choose_device(request: str | None):
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise NoDeviceError(f"no OpenCL platform found ({exc}); {_INSTALL_HINT}") from exc
    devices = []
    for p in platforms:
        try:
            devices += [(p, d) for d in p.get_devices()]
        except cl.Error:
            continue
    if not devices:
        raise NoDeviceError(f"OpenCL platforms exist but list no device; {_INSTALL_HINT}")
    if request:
        hits = [(p, d) for p, d in devices if request.lower() in f"{p.name} / {d.name}".lower()]
        if not hits:
            names = "; ".join(f"{p.name} / {d.name}" for p, d in devices)
            raise NoDeviceError(f"no OpenCL device matches {request!r}; visible: {names}")
        return hits[0][1]
    for p, d in devices:
        if "portable computing language" in p.name.lower() and d.type & cl.device_type.CPU:
            return d
    return devices[0][1]


@dataclass
class DeviceArray:
    """A torch tensor and the OpenCL buffer that holds (or aliases) its data."""

    tensor: torch.Tensor
    buf: object
    copy_back: bool = False


@dataclass
class Runtime:
    device: object
    context: object = None
    queue: object = None
    unified: bool = False
    bytes_transferred: int = 0
    programs: dict = field(default_factory=dict)
    kernels: dict = field(default_factory=dict)
    raster: str | None = None  # force the "cpu" or "gpu" rasterizer variant (see ops.raster_variant)
    # Bit-reproducible backward (fixed-order gradient sums) instead of atomics;
    # COIN_CL_DETERMINISTIC=0 switches it off.
    deterministic: bool = field(default_factory=lambda: os.environ.get("COIN_CL_DETERMINISTIC", "1") != "0")
    poison: bool = False  # tests: fill outputs with NaN / INT32_MIN so unwritten elements show
    extensions: frozenset = frozenset()

    def __post_init__(self):
        import pyopencl as cl

        self.context = cl.Context([self.device])
        self.profile = _env_flag("COIN_CL_PROFILE")
        props = cl.command_queue_properties.PROFILING_ENABLE if self.profile else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self.kernel_times: dict[str, list[float]] = {}
        self.unified = bool(self.device.host_unified_memory) and not _env_flag("COIN_CL_NO_ZERO_COPY")
        self.extensions = frozenset(self.device.extensions.split())
        self._lock = threading.Lock()
        log.debug("OpenCL device: %s (unified memory: %s)", self.name, self.unified)

    @property
    def name(self) -> str:
        return f"{self.device.platform.name} / {self.device.name}"

    @property
    def is_cpu(self) -> bool:
        import pyopencl as cl

        return bool(self.device.type & cl.device_type.CPU)

    def program(self, filename: str, defines: dict[str, object] | None = None):
        """Build (once per variant) and return the program in kernels/<filename>.

        Only the variants a scene uses are compiled: channel counts and knobs are -D defines.
        """
        import pyopencl as cl

        key = (filename, tuple(sorted((defines or {}).items())))
        with self._lock:
            prg = self.programs.get(key)
            if prg is None:
                d = kernel_dir()
                src = (d / filename).read_text()
                opts = [f"-I{d}"] + [f"-D{k}={v}" for k, v in sorted((defines or {}).items())]
                log.debug("building %s with %s", filename, opts)
                try:
                    prg = cl.Program(self.context, src).build(options=opts)
                except cl.RuntimeError as exc:
                    raise RuntimeError(f"OpenCL build of {filename} failed on {self.name}: {exc}") from exc
                self.programs[key] = prg
        return prg

    def kernel(self, filename: str, name: str, defines: dict[str, object] | None = None):
        """A cached `cl.Kernel` (retrieving a kernel from a program re-creates it every time)."""
        import pyopencl as cl

        key = (filename, name, tuple(sorted((defines or {}).items())))
        k = self.kernels.get(key)
        if k is None:
            k = self.kernels[key] = cl.Kernel(self.program(filename, defines), name)
        return k

    def launch(self, filename: str, name: str, global_size, local_size, *args, defines=None) -> None:
        """Enqueue kernel `name` of kernels/<filename> (variant `defines`) with `args`.

        With COIN_CL_PROFILE=1 each launch waits for its event and records its device time in
        `kernel_times[name]` (seconds), which is how the benchmark splits a frame by kernel.
        """
        ev = self.kernel(filename, name, defines)(self.queue, global_size, local_size, *args)
        if self.profile:
            ev.wait()
            self.kernel_times.setdefault(name, []).append((ev.profile.end - ev.profile.start) * 1e-9)

    # -- shared buffers ---------------------------------------------------------------------
    def array(self, tensor: torch.Tensor, mode: str = "in") -> DeviceArray:
        """Wrap a contiguous CPU tensor as a device buffer (aliased when memory is unified).

        mode says what crosses when memory is not unified: "in" (the kernel reads it), "out" (the
        kernel writes every element; copied back by `finish`), "inout" (read-modify-write, e.g.
        accumulators; both ways) or "scratch" (device-only working memory; neither way).
        """
        import pyopencl as cl

        if mode not in ("in", "out", "inout", "scratch"):
            raise ValueError(f"unknown buffer mode {mode!r}")
        if not tensor.is_contiguous() or tensor.device.type != "cpu":
            raise ValueError("runtime.array needs a contiguous CPU tensor")
        mf = cl.mem_flags
        nbytes = tensor.numel() * tensor.element_size()
        if nbytes == 0:
            # OpenCL has no zero-sized buffers; a kernel never reads this one.
            return DeviceArray(tensor, cl.Buffer(self.context, mf.READ_WRITE, 16))
        host = tensor.detach().numpy()
        if self.unified:
            return DeviceArray(tensor, cl.Buffer(self.context, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=host))
        buf = cl.Buffer(self.context, mf.READ_WRITE, nbytes)
        if mode in ("in", "inout"):
            cl.enqueue_copy(self.queue, buf, host)
            self.bytes_transferred += nbytes
        return DeviceArray(tensor, buf, copy_back=mode in ("out", "inout"))

    def empty(self, *shape: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """An output tensor; filled with NaN (floats) or INT32_MIN (ints) when poisoning."""
        if not self.poison:
            return torch.empty(shape, dtype=dtype)
        fill = float("nan") if dtype.is_floating_point else torch.iinfo(dtype).min
        return torch.full(shape, fill, dtype=dtype)

    def finish(self, *arrays: DeviceArray) -> None:
        """Wait for the queue and bring outputs back to their tensors (a no-op copy when unified)."""
        import pyopencl as cl

        for a in arrays:
            if a.copy_back and a.tensor.numel():
                cl.enqueue_copy(self.queue, a.tensor.detach().numpy(), a.buf)
                self.bytes_transferred += a.tensor.numel() * a.tensor.element_size()
        self.queue.finish()


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").lower() not in ("", "0", "false", "no")


_RUNTIMES: dict[str, Runtime] = {}


def get_runtime(device: str | None = None) -> Runtime:
    """The process-wide runtime for `device` (default: $COIN_CL_DEVICE, else PoCL's CPU device)."""
    key = device if device is not None else os.environ.get("COIN_CL_DEVICE", "")
    rt = _RUNTIMES.get(key)
    if rt is None:
        rt = _RUNTIMES[key] = Runtime(_choose_device(key or None))
        log.info("coin-cl OpenCL device: %s", rt.name)
    return rt


def as_f32(t: torch.Tensor) -> torch.Tensor:
    """Contiguous float32 detached copy-or-view, the layout every kernel reads."""
    return t.detach().to(torch.float32).contiguous()
