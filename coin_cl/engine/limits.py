"""Device limits the kernels depend on, queried once per device, and what each kernel needs.

Which limits matter (docs/DESIGN.md section 3, the runtime layer; the renderer of section 4):
- CL_DEVICE_MAX_WORK_GROUP_SIZE and each kernel's CL_KERNEL_WORK_GROUP_SIZE: the GPU rasterizer
  runs one work-group per 16x16 tile, 256 work-items wide by default; the per-item kernels
  (project, bin, decode, reduce, SSIM, warp) ask for 64 but use neither local memory nor barriers,
  so any smaller power of two gives the same result.
- CL_DEVICE_LOCAL_MEM_SIZE against the local arrays of the GPU rasterizer (the only kernel file
  with __local memory), which scale with its work-group width.
- CL_DEVICE_MAX_MEM_ALLOC_SIZE against every buffer (the largest are the pair-sized arrays).
No kernel uses images, so the image size limits do not apply.

A device whose limits are below the smallest variant gets a `DeviceLimitError` naming the device,
the limit and what to do; `devices.default_rank` ranks such a GPU behind the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

from coin_cl.engine import constants as cst

# Work-group widths of the GPU rasterizer, widest first: each divides the tile's 256 pixels, and a
# work-group narrower than a tile walks the tile in TILE_PIXELS / width passes (rasterize_gpu.cl).
TILE_PIXELS = cst.TILE_SIZE * cst.TILE_SIZE
RASTER_GPU_GROUPS = (256, 128, 64, 32, 16)
RASTER_GPU_ROWS = 8  # quantities reduced per pass in the backward (ROWS in rasterize_gpu.cl)


@dataclass(frozen=True)
class DeviceLimits:
    """The limits of one device that the kernels depend on (bytes, work-items)."""

    max_work_group_size: int
    local_mem_size: int
    max_mem_alloc_size: int
    local_mem_is_local: bool = True  # CL_DEVICE_LOCAL_MEM_TYPE is LOCAL (dedicated), not GLOBAL


def query_limits(device) -> DeviceLimits:
    """The `DeviceLimits` of a pyopencl device."""
    import pyopencl as cl

    return DeviceLimits(
        max_work_group_size=int(device.max_work_group_size),
        local_mem_size=int(device.local_mem_size),
        max_mem_alloc_size=int(device.max_mem_alloc_size),
        local_mem_is_local=device.local_mem_type == cl.device_local_mem_type.LOCAL,
    )


def raster_gpu_local_bytes(kernel: str, group: int) -> int:
    """Bytes of __local memory that `kernel` ("rasterize_fwd" or "rasterize_bwd") of
    rasterize_gpu.cl declares at work-group width `group` (the batch of splats: a float4 of
    position and opacity, a float4 conic and an int id per work-item; the backward adds the
    ROWS x group reduction rows, group + ROWS partial sums and three ints, the forward one
    int)."""
    batch = group * (16 + 16 + 4)
    if kernel == "rasterize_fwd":
        return batch + 4
    if kernel == "rasterize_bwd":
        return batch + RASTER_GPU_ROWS * group * 4 + (group + RASTER_GPU_ROWS) * 4 + 3 * 4
    raise ValueError(f"unknown rasterize kernel {kernel!r}")


def min_raster_gpu_local_bytes() -> int:
    """Local memory the narrowest GPU rasterizer variant needs (its backward): below this a
    device cannot run rasterize_gpu.cl at all."""
    return raster_gpu_local_bytes("rasterize_bwd", RASTER_GPU_GROUPS[-1])


def describe(device_name: str, what: str, have: object, need: object, todo: str) -> str:
    """One line naming the device, the limit and what to do."""
    return f"OpenCL device {device_name!r}: {what} is {have}, below the {need} needed; {todo}"
