"""OpenCL runtime: one context and queue per device, a per-variant program cache, shared buffers.

The device itself is found and chosen by `coin_cl.engine.devices` (docs/DESIGN.md section 3, the runtime
layer); `get_runtime` keeps one `Runtime` per requested device for the whole process.

Buffers: on a host-unified-memory device (the CPU implementations) a `cl.Buffer` is created over
the torch tensor's own memory (USE_HOST_PTR), so nothing is copied and `queue.finish()` is the
hand-over point. Elsewhere (a discrete GPU; forced on any device by COIN_CL_DISCRETE=1, so CI runs
this path) inputs are copied into device-only buffers and outputs copied back, and every copy's
bytes and device time are counted in `Runtime.transfers` (`coin_cl.engine.transfers`); on a GPU
the copies go through page-locked memory (`coin_cl.engine.pinned`), where outputs are allocated.
An output a kernel wrote stays on the device beside its tensor (`remember`): a later op handed
that same, unchanged tensor (`input`) reads the buffer instead of copying it in again, so a view's
projected splats and its gradients cross once per step, not once per op.

Limits: every launch is checked against the device's and the kernel's work-group size, every
buffer against the device's largest allocation (`coin_cl.engine.limits`).
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
import threading
import warnings
import weakref
from dataclasses import dataclass, field

import torch

from coin_cl.engine import devices, kernel_cache, pinned
from coin_cl.engine.errors import DeviceLimitError
from coin_cl.engine.limits import DeviceLimits, describe, query_limits
from coin_cl.engine.transfers import TransferStats

log = logging.getLogger(__name__)


@dataclass
class DeviceArray:
    """A torch tensor and the OpenCL buffer that holds (or aliases) its data."""

    tensor: torch.Tensor
    buf: object
    copy_back: bool = False
    keep: bool = False  # remembered beside its tensor once copied back (`Runtime.remember`)


@dataclass
class Runtime:
    device: object
    context: object = None
    queue: object = None
    unified: bool = False
    # Device-only buffers and counted copies even where memory is host-unified (None: from
    # COIN_CL_DISCRETE / COIN_CL_NO_ZERO_COPY, else from the device's host_unified_memory).
    discrete: bool | None = None
    transfers: TransferStats = field(default_factory=TransferStats)
    programs: dict = field(default_factory=dict)
    kernels: dict = field(default_factory=dict)
    variant_fits: dict = field(default_factory=dict)  # (file, kernel, defines) -> (width, defines)
    raster: str | None = None  # force the "cpu" or "gpu" rasterizer variant (see ops.raster_variant)
    # Bit-reproducible backward (fixed-order gradient sums) instead of atomics;
    # COIN_CL_DETERMINISTIC=0 switches it off.
    deterministic: bool = field(default_factory=lambda: os.environ.get("COIN_CL_DETERMINISTIC", "1") != "0")
    poison: bool = False  # tests: fill outputs with NaN / INT32_MIN so unwritten elements show
    # Copies of the discrete path through page-locked staging (`coin_cl.engine.pinned`); None: from
    # COIN_CL_PINNED (0 or 1), else on for a discrete GPU and off for a CPU device run discretely.
    pinned: bool | None = None
    extensions: frozenset = frozenset()

    def __post_init__(self):
        import pyopencl as cl

        self.context = cl.Context([self.device])
        self.profile = _env_flag("COIN_CL_PROFILE")
        if self.discrete is None:
            forced = _env_flag("COIN_CL_DISCRETE") or _env_flag("COIN_CL_NO_ZERO_COPY")
            self.discrete = forced or not devices.host_unified(self.device)
        elif not self.discrete and not devices.host_unified(self.device):
            # Aliasing host memory is coherent only where the device shares it; elsewhere
            # USE_HOST_PTR needs map/unmap around every host access, which this runtime never does.
            raise ValueError(f"{self.name} has no host-unified memory: it runs the discrete path only")
        self.unified = not self.discrete
        if self.pinned is None:
            env = os.environ.get("COIN_CL_PINNED", "")
            self.pinned = _env_flag("COIN_CL_PINNED") if env else not (self.device.type & cl.device_type.CPU)
        self.pinned = bool(self.pinned and self.discrete)
        # Profiling times the copies of the discrete path (and the kernels with COIN_CL_PROFILE).
        props = cl.command_queue_properties.PROFILING_ENABLE if self.profile or self.discrete else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self.limits: DeviceLimits = query_limits(self.device)
        self.kernel_times: dict[str, list[float]] = {}
        self.extensions = frozenset(self.device.extensions.split())
        self._lock = threading.Lock()
        self._float_atomics: bool | None = None
        self.n_finish = 0  # host waits, counted (the benchmark reports them per frame)
        self._in_flight: list = []  # arguments of launches not yet waited for
        self._kernel_info: dict = {}
        # Tensors whose content a device buffer already holds (`remember`), by data pointer:
        # data_ptr -> (weak reference to the tensor, its version then, bytes, buffer).
        self._resident: dict[int, tuple] = {}
        self._pool = pinned.PinnedPool(self.context, self.queue) if self.pinned else None
        self._blocks: list = []  # page-locked blocks of copies not yet waited for
        self._pinned_ptrs: set[int] = set()  # data pointers of live `empty` tensors in pinned blocks
        log.debug("OpenCL device: %s (unified memory: %s)", self.name, self.unified)

    @property
    def name(self) -> str:
        return devices.device_label(self.device)

    @property
    def bytes_transferred(self) -> int:
        """Bytes copied between host and device so far (0 on the unified path)."""
        return self.transfers.bytes

    def kernel_limits(
        self, filename: str, name: str, defines: dict[str, object] | None = None
    ) -> tuple[int, int]:
        """(CL_KERNEL_WORK_GROUP_SIZE, CL_KERNEL_LOCAL_MEM_SIZE) of a kernel variant on this device:
        the widest work-group it can be launched with and the local memory it uses (bytes)."""
        import pyopencl as cl

        k = self.kernel(filename, name, defines)
        info = cl.kernel_work_group_info
        return (int(k.get_work_group_info(info.WORK_GROUP_SIZE, self.device)),
                int(k.get_work_group_info(info.LOCAL_MEM_SIZE, self.device)))  # fmt: skip

    def _fit_local(self, filename: str, name: str, defines, local_size):
        """The work-group size to launch with: `local_size` where it fits the device and the
        kernel; narrower (the largest power of two that fits) for kernels whose source does not
        depend on the work-group (`group_bound`; their global sizes are multiples of 64, so every
        power of two below still divides them); `DeviceLimitError` where a kernel needs exactly
        `local_size` and it does not fit."""
        if local_size is None:
            return None
        key = (filename, name, tuple(sorted((defines or {}).items())), tuple(local_size))
        fit = self._kernel_info.get(key)
        if fit is None:
            want = 1
            for s in local_size:
                want *= int(s)
            wg, _ = self.kernel_limits(filename, name, defines)
            limit = min(wg, self.limits.max_work_group_size)
            if want <= limit:
                fit = tuple(local_size)
            elif group_bound(filename) or len(local_size) != 1:
                raise DeviceLimitError(
                    describe(self.name, f"the work-group size {name} ({filename}) can be launched with",
                             limit, want, "this kernel has no narrower variant; choose another device with "
                             "COIN_CL_DEVICE (`coin-cl doctor` lists them)")
                )  # fmt: skip
            else:
                fit = (1 << (limit.bit_length() - 1),)  # the largest power of two that fits
                log.info(
                    "%s on %s: work-group %d narrowed to %d (device limit)", name, self.name, want, fit[0]
                )
            self._kernel_info[key] = fit
        return fit

    @property
    def float_atomics(self) -> bool:
        """Whether the device has a working float atomic add (probed once). COIN_CL_FLOAT_ATOMICS=0
        keeps the compare-and-swap loop even where it does."""
        if self._float_atomics is None:
            wanted = os.environ.get("COIN_CL_FLOAT_ATOMICS", "1") != "0"
            self._float_atomics = wanted and devices.probe_float_atomics(self.device)
        return self._float_atomics

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
                d = devices.kernel_dir()
                src = (d / filename).read_text()
                opts = [f"-I{d}"] + [f"-D{k}={v}" for k, v in sorted((defines or {}).items())]
                if "USE_FLOAT_ATOMICS" in (defines or {}):
                    opts += devices.FLOAT_ATOMICS_OPTIONS  # atomic_float needs OpenCL C 2.0+
                log.debug("building %s with %s", filename, opts)
                try:
                    with warnings.catch_warnings():
                        # Some compilers (Intel's) always print a build log; it is not a problem.
                        warnings.simplefilter("ignore", cl.CompilerWarning)
                        prg = kernel_cache.build(self.context, src, opts)
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
        local_size = self._fit_local(filename, name, defines, local_size)
        ev = self.kernel(filename, name, defines)(self.queue, global_size, local_size, *args)
        if self.profile:
            ev.wait()
            self.kernel_times.setdefault(name, []).append((ev.profile.end - ev.profile.start) * 1e-9)

    def run(
        self,
        filename: str,
        name: str,
        global_size: tuple[int, ...],
        local_size: tuple[int, ...] | None,
        args: list,
        defines: dict[str, object] | None = None,
        wait: bool = True,
    ) -> None:
        """Launch kernel `name` with a declarative argument list, then wait for its outputs.

        Each entry of `args` is a numpy scalar (passed by value), a tensor (read by the kernel:
        mode "in"), a (tensor, mode) pair with mode "out", "inout", "acc" or "scratch" (see `array`), or
        a `DeviceArray` from `array` when one buffer must outlive a launch (a scratch buffer one
        kernel writes and the next reads).
        With `wait` (the default) the queue is finished and outputs copied back when the host is
        about to read them; pass wait=False when the next launch on this in-order queue is the
        only reader.
        """
        bufs, outs = [], []
        for a in args:
            if isinstance(a, DeviceArray):  # already wrapped: shared with another launch
                bufs.append(a.buf)
                if a.copy_back:
                    outs.append(a)
                continue
            if isinstance(a, torch.Tensor):
                a = (a, "in")
            if isinstance(a, tuple):
                arr = self.array(a[0], mode=a[1])
                bufs.append(arr.buf)
                if arr.copy_back:
                    outs.append(arr)
            else:
                bufs.append(a)
        self.launch(filename, name, global_size, local_size, *bufs, defines=defines)
        if wait:
            self.finish(*outs)
        else:
            # The kernel may still read or write these: keep the tensors (whose memory the
            # buffers alias or are copied from) and buffers alive until the next finish.
            self._in_flight.append((args, bufs))

    # -- shared buffers ---------------------------------------------------------------------
    def array(self, tensor: torch.Tensor, mode: str = "in", keep: bool = False) -> DeviceArray:
        """Wrap a contiguous CPU tensor as a device buffer (aliased when memory is unified).

        mode says what crosses when memory is not unified: "in" (the kernel reads it), "out" (the
        kernel writes every element; copied back by `finish`), "inout" (read-modify-write; both
        ways), "acc" (an accumulator the kernel adds into: the tensor holds zeros, the device
        buffer is zero-filled there rather than copied in; copied back), "scratch" (device-only
        working memory; neither way) or "zeros" (device-only working memory starting at zero: the
        tensor holds zeros; neither way). `keep` (an output the next op reads): once `finish` has
        copied it back, the buffer is remembered beside the tensor (`remember`).
        """
        import numpy as np
        import pyopencl as cl

        if mode not in ("in", "out", "inout", "acc", "scratch", "zeros"):
            raise ValueError(f"unknown buffer mode {mode!r}")
        if mode in ("acc", "zeros") and self.poison and bool(tensor.any()):  # tests check the promise
            raise ValueError(f"runtime.array(mode={mode!r}) needs a tensor of zeros")
        if not tensor.is_contiguous() or tensor.device.type != "cpu":
            raise ValueError("runtime.array needs a contiguous CPU tensor")
        mf = cl.mem_flags
        nbytes = tensor.numel() * tensor.element_size()
        if nbytes == 0:
            # OpenCL has no zero-sized buffers; a kernel never reads this one.
            return DeviceArray(tensor, cl.Buffer(self.context, mf.READ_WRITE, 16))
        if nbytes > self.limits.max_mem_alloc_size:
            raise DeviceLimitError(
                describe(self.name, "CL_DEVICE_MAX_MEM_ALLOC_SIZE (bytes)", self.limits.max_mem_alloc_size,
                         nbytes, f"a buffer of shape {tuple(tensor.shape)} does not fit: render fewer "
                         "splats or smaller images, or choose another device with COIN_CL_DEVICE")
            )  # fmt: skip
        host = tensor.detach().numpy()
        if self.unified:
            return DeviceArray(tensor, cl.Buffer(self.context, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=host))
        buf = cl.Buffer(self.context, mf.READ_WRITE, nbytes)
        # Poisoned outputs cross too, so an element a kernel leaves unwritten shows on this path.
        if mode in ("in", "inout") or (mode == "out" and self.poison):
            block = self._staging(tensor)
            if block is not None:
                self._blocks.append(block)
                host = pinned.fill(block, tensor)
            ev = cl.enqueue_copy(self.queue, buf, host, is_blocking=False)
            self.transfers.add(nbytes, ev, inbound=True)
            self._in_flight.append(host)  # the copy reads it until the next finish
        elif mode in ("acc", "zeros"):
            cl.enqueue_fill_buffer(self.queue, buf, np.zeros(1, np.uint8), 0, nbytes)
        copy_back = mode in ("out", "inout", "acc")
        if copy_back:
            self._forget(tensor.data_ptr())  # its memory is about to change behind its version counter
        return DeviceArray(tensor, buf, copy_back=copy_back, keep=keep and copy_back)

    def input(self, tensor: torch.Tensor, dtype: torch.dtype = torch.float32) -> DeviceArray:
        """`tensor` as a kernel input of `dtype`: the buffer an earlier launch wrote it into when it
        is the very tensor `remember` was given and has not been modified since (its version
        counter, which in-place torch ops advance); otherwise a contiguous `dtype` copy, uploaded.
        """
        if not self.unified and self._resident and tensor.dtype == dtype:
            hit = self._resident.get(tensor.data_ptr())
            if hit is not None and hit[0]() is tensor and hit[1] == _version(tensor):
                self.transfers.reused += hit[2]
                return DeviceArray(tensor.detach(), hit[3])
        return self.array(tensor.detach().to(dtype).contiguous())

    def remember(self, tensor: torch.Tensor, arr: DeviceArray) -> None:
        """Record that `arr`'s buffer holds `tensor`'s content (call after the launch that wrote it
        has finished and been copied back): `input(tensor)` then reuses the buffer for as long as
        both live and the tensor is unchanged. Nothing to do on host-unified memory."""
        if self.unified or arr.tensor.data_ptr() != tensor.data_ptr() or arr.tensor.dtype != tensor.dtype:
            return
        version = _version(tensor)
        if version is None or not tensor.is_contiguous():
            return
        ptr, nbytes = tensor.data_ptr(), tensor.numel() * tensor.element_size()
        ref = weakref.ref(tensor, functools.partial(_drop_entry, self._resident, ptr))
        self._resident[ptr] = (ref, version, nbytes, arr.buf)

    def _forget(self, ptr: int) -> None:
        """Drop the remembered buffer of any tensor whose memory starts at `ptr`."""
        if self._resident:
            self._resident.pop(ptr, None)

    def _staging(self, tensor: torch.Tensor) -> pinned.PinnedBlock | None:
        """A page-locked block to copy `tensor` through, or None: no staging, no room in the pool,
        or the tensor already in page-locked memory (`empty`), which the copy then uses directly."""
        if self._pool is None or tensor.data_ptr() in self._pinned_ptrs:
            return None
        return self._pool.take(tensor.numel() * tensor.element_size())

    def reuse(self, tensor: torch.Tensor, buf) -> DeviceArray:
        """The buffer an earlier launch filled for `tensor`, read again by a later one (the
        backward reading what its forward uploaded or computed): nothing crosses. Only for a
        tensor nobody has written since that launch."""
        return DeviceArray(tensor, buf)

    def empty(self, *shape: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """An output tensor; filled with NaN (floats) or INT32_MIN (ints) when poisoning. With
        page-locked staging it lives in a page-locked block (while the pool has room), so that the
        copy back is one DMA transfer straight into it."""
        if self.poison:
            fill = float("nan") if dtype.is_floating_point else torch.iinfo(dtype).min
            return torch.full(shape, fill, dtype=dtype)
        if self._pool is not None:
            t = self._pinned_empty(shape, dtype)
            if t is not None:
                return t
        return torch.empty(shape, dtype=dtype)

    def scratch(self, *shape: int, dtype: torch.dtype = torch.float32) -> DeviceArray:
        """Working memory one kernel writes and a later one reads: device-only (nothing crosses);
        on host-unified memory, an uninitialised tensor's."""
        return self.array(torch.empty(shape, dtype=dtype), "scratch")

    def zeros(self, *shape: int, dtype: torch.dtype = torch.float32) -> DeviceArray:
        """Working memory starting at zero, device-only (mode "zeros"): on the discrete path the
        device fills it and no host tensor of its size is written; on host-unified memory it is a
        zeroed tensor's."""
        zeroed = self.unified or self.poison  # poisoning checks the "zeros" promise on the tensor
        return self.array((torch.zeros if zeroed else torch.empty)(shape, dtype=dtype), "zeros")

    def _pinned_empty(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor | None:
        nbytes = math.prod(shape) * dtype.itemsize
        block = self._pool.take(nbytes) if nbytes else None
        if block is None:
            return None
        # A fresh array object over the block: the tensor's storage holds it, so it dies with the
        # last view of the tensor, and only then does the block go back to the pool.
        host = block.host[:nbytes]
        t = torch.from_numpy(host).view(dtype).view(shape)
        ptr = t.data_ptr()
        self._pinned_ptrs.add(ptr)
        weakref.finalize(host, self._release_pinned, block, ptr)
        return t

    def _release_pinned(self, block: pinned.PinnedBlock, ptr: int) -> None:
        self._pinned_ptrs.discard(ptr)
        self._forget(ptr)
        self._pool.give(block)

    def finish(self, *arrays: DeviceArray) -> None:
        """Wait for the queue and bring outputs back to their tensors (a no-op copy when unified)."""
        import pyopencl as cl

        self.n_finish += 1
        in_flight, self._in_flight = self._in_flight, []
        blocks, self._blocks = self._blocks, []
        drains = []  # (copy event, page-locked block, the tensor it is copied into after the event)
        for a in arrays:
            if a.copy_back and a.tensor.numel():
                host = a.tensor.detach().numpy()
                block = self._staging(a.tensor)
                if block is not None:
                    blocks.append(block)
                    host = block.view(host.nbytes)
                ev = cl.enqueue_copy(self.queue, host, a.buf, is_blocking=False)
                self.transfers.add(host.nbytes, ev, inbound=False)
                in_flight.append(host)
                if block is not None:
                    drains.append((ev, block, a.tensor))
        for ev, block, tensor in drains:  # each drains while the later copies still run
            ev.wait()
            pinned.drain(block, tensor)
        self.queue.finish()
        self.transfers.settle()
        for block in blocks:
            self._pool.give(block)
        for a in arrays:
            if a.keep:
                self.remember(a.tensor, a)
        del in_flight  # released only once the queue has drained


# What every `device=` argument takes: an OpenCL `Runtime` (used as is), a device-name substring
# (matched by `devices.choose_device`), or None for the default device ($COIN_CL_DEVICE, else the
# first that builds the kernels); `resolve_device` turns one into a Runtime.
DeviceLike = Runtime | str | None


# What makes a kernel's result depend on its work-group: local arrays, barriers, a required size,
# or reading the group's geometry. Decided from the source because the driver's answers differ:
# NVIDIA's OpenCL reports CL_KERNEL_LOCAL_MEM_SIZE = 1 byte for kernels that declare no local
# memory (seen on an H200, driver 580.159), which made every per-item kernel look unnarrowable.
_GROUP_BOUND = re.compile(
    r"__local\b|\blocal\s+\w+\s*\*|barrier\s*\(|reqd_work_group_size|get_local_id|get_local_size"
    r"|get_group_id|get_num_groups|work_group_"
)


@functools.cache
def group_bound(filename: str) -> bool:
    """Whether kernels/<filename> (with the headers it includes from kernels/) has any kernel whose
    result depends on the work-group size, so it can only run at the size it was written for."""
    d = devices.kernel_dir()
    src = (d / filename).read_text()
    for inc in re.findall(r'#include\s+"([^"]+)"', src):
        if (d / inc).is_file():
            src += (d / inc).read_text()
    return bool(_GROUP_BOUND.search(src))


def _version(tensor: torch.Tensor) -> int | None:
    """The tensor's version counter (None for inference-mode tensors, which have none)."""
    try:
        return tensor._version
    except RuntimeError:
        return None


def _drop_entry(table: dict, ptr: int, ref: weakref.ref) -> None:
    """Weak-reference callback: the tensor is gone, and with it the need for its buffer."""
    entry = table.get(ptr)
    if entry is not None and entry[0] is ref:
        del table[ptr]


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").lower() not in ("", "0", "false", "no")


_RUNTIMES: dict[str, Runtime] = {}


def get_runtime(device: str | None = None) -> Runtime:
    """The process-wide runtime for `device` (default: $COIN_CL_DEVICE, else the first device that
    builds kernels in `devices.default_rank` order)."""
    key = device if device is not None else os.environ.get("COIN_CL_DEVICE", "")
    rt = _RUNTIMES.get(key)
    if rt is None:
        rt = _RUNTIMES[key] = Runtime(devices.choose_device(key or None))
        log.info("coin-cl OpenCL device: %s", rt.name)
    return rt


def resolve_device(device: DeviceLike) -> Runtime:
    """The runtime for `device`: a Runtime as is, a name substring, or None for the default."""
    if isinstance(device, Runtime):
        return device
    if device is None or isinstance(device, str):
        return get_runtime(device)
    raise TypeError(f"device must be a Runtime, a device name or None, not {type(device).__name__}")


def as_f32(t: torch.Tensor) -> torch.Tensor:
    """Contiguous float32 detached copy-or-view, the layout every kernel reads."""
    return t.detach().to(torch.float32).contiguous()
