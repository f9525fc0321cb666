"""Tile rasterizer (kernels/rasterize_cpu.cl, kernels/rasterize_gpu.cl): front-to-back alpha
compositing of binned splats, forward and backward."""

from __future__ import annotations

import os
from typing import Any

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.errors import DeviceLimitError
from coin_cl.engine.limits import RASTER_GPU_GROUPS, TILE_PIXELS, describe, raster_gpu_local_bytes
from coin_cl.engine.ops._util import i32
from coin_cl.engine.ops.bin import TileBins, bin_tiles
from coin_cl.engine.ops.reduce import reduce_pair_grads
from coin_cl.engine.runtime import Runtime, as_f32, resolve_device


def kernel_variant(channels: int, defines: dict[str, Any]) -> dict[str, Any]:
    """Build defines of a rasterize program: the channel count and the user's knobs (the
    DETERMINISTIC choice is added by the backward only, so the forward compiles once)."""
    return {"NUM_CHANNELS": channels, **{k: v for k, v in defines.items() if k != "DETERMINISTIC"}}


def deterministic(rt: Runtime, defines: dict[str, Any]) -> bool:
    """Whether the backward sums per-tile gradient shares in a fixed order (bit-reproducible)
    rather than with atomics: `defines["DETERMINISTIC"]`, else `rt.deterministic`."""
    return bool(int(defines.get("DETERMINISTIC", rt.deterministic)))


def raster_variant(rt: Runtime) -> tuple[str, int]:
    """(kernel file, work-items per tile) of the rasterizer for this device.

    CPUs get one work-item per tile that vectorises over pixel rows (rasterize_cpu.cl); GPUs one
    work-item per pixel with local-memory batches and reductions (rasterize_gpu.cl).
    COIN_CL_RASTER=cpu|gpu (or `rt.raster`) overrides the choice; both run on any device.
    """
    choice = rt.raster or os.environ.get("COIN_CL_RASTER") or ("cpu" if rt.is_cpu else "gpu")
    if choice not in ("cpu", "gpu"):
        raise ValueError(f"COIN_CL_RASTER={choice!r}: use 'cpu' or 'gpu'")
    return (f"rasterize_{choice}.cl", 1 if choice == "cpu" else cst.TILE_SIZE * cst.TILE_SIZE)


def fit_variant(rt: Runtime, src: str, kernel: str, variant: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    """(work-group width, build defines) of `kernel` in `src` that this device can run.

    The CPU rasterizer runs one work-item per tile. The GPU rasterizer is 256 wide unless the
    device's work-group limit, the built kernel's own limit (CL_KERNEL_WORK_GROUP_SIZE) or the
    local memory its arrays need at that width is below it; then the widest of RASTER_GPU_GROUPS
    that fits is built with -DGROUP (the tile is walked in bands; same results within float32
    rounding). None fitting is a `DeviceLimitError` naming the device and the limit.
    """
    if src != "rasterize_gpu.cl":
        return 1, variant
    key = (src, kernel, tuple(sorted(variant.items())))
    hit = rt.variant_fits.get(key)
    if hit is not None:
        return hit
    lim = rt.limits
    for g in RASTER_GPU_GROUPS:
        if g > lim.max_work_group_size or raster_gpu_local_bytes(kernel, g) > lim.local_mem_size:
            continue
        d = variant if g == TILE_PIXELS else {**variant, "GROUP": g}
        wg, local_bytes = rt.kernel_limits(src, kernel, d)
        if g <= wg and local_bytes <= lim.local_mem_size:
            rt.variant_fits[key] = (g, d)
            return g, d
    need = raster_gpu_local_bytes(kernel, RASTER_GPU_GROUPS[-1])
    raise DeviceLimitError(
        describe(rt.name, f"the work-group size / local memory (B) for {kernel}",
                 f"{lim.max_work_group_size} / {lim.local_mem_size}", f"{RASTER_GPU_GROUPS[-1]} / {need}",
                 "use the CPU rasterizer on this device (COIN_CL_RASTER=cpu) or another device "
                 "(COIN_CL_DEVICE)")
    )  # fmt: skip


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, opacities, features, bins, width, height, background, stats, rt, defines
    ):
        C = features.shape[1]
        bg = torch.zeros(C) if background is None else as_f32(background)
        ts = cst.TILE_SIZE
        stride, rows = bins.tiles_x * ts, bins.tiles_y * ts
        plane = stride * rows
        img, t_final = rt.empty(C, rows, stride), rt.empty(rows, stride)
        # `last` (where each pixel's backward starts) crosses only when the caller asks for stats.
        last = (rt.empty if stats is not None else torch.empty)(rows, stride, dtype=torch.int32)
        src, _ = raster_variant(rt)
        local, variant = fit_variant(rt, src, "rasterize_fwd", kernel_variant(C, defines))
        # Kept for the backward, which reads them again without another copy (discrete memory).
        # The splats usually are already there: `project` (and `decode`) left their outputs.
        kept = [rt.input(t) for t in (means2d, conics, opacities, features)]
        kept += [rt.array(bg), rt.array(t_final, "out"),
                 rt.array(last, "scratch" if stats is None else "out")]  # fmt: skip
        m2, con, op, ft = (a.tensor for a in kept[:4])
        a_m2, a_con, a_op, a_ft, a_bg, a_t, a_last = kept
        rt.run(
            src, "rasterize_fwd", (bins.n_tiles * local,), (local,),
            [i32(bins.tiles_x), i32(stride), i32(plane), *bins.arrays(rt, "tile_start", "tile_end", "ids"),
             a_m2, a_con, a_op, *bins.arrays(rt, "extents"), a_ft, a_bg, (img, "out"), a_t, a_last],
            defines=variant,
        )  # fmt: skip
        if stats is not None:
            # last: per pixel, how many splats of its tile list were composited (1-based index
            # of the last contributor); the backward pass starts there.
            stats.update(n_pairs=bins.n_pairs, n_visible=bins.n_visible, last=last[:height, :width])
        ctx.save_for_backward(m2, con, op, ft, bg, t_final, last)
        ctx.meta = (width, height, rt, defines, bins, features.dtype, background is not None)
        ctx.bufs = [a.buf for a in kept]  # buffers only: a tensor here could make a reference cycle
        out_img = img[:, :height, :width].permute(1, 2, 0).to(features.dtype)
        out_alpha = (1.0 - t_final[:height, :width]).to(features.dtype)
        return out_img, out_alpha

    @staticmethod
    def backward(ctx, v_img, v_alpha):
        m2, con, op, ft, bg, t_final, last = ctx.saved_tensors
        width, height, rt, defines, bins, dtype, has_bg = ctx.meta
        n, C = ft.shape
        rows, stride = t_final.shape
        plane = rows * stride
        # Pad the cotangents to whole tiles, channel-major, as the kernels read them.
        g_img = torch.zeros(C, rows, stride)
        if v_img is not None:
            g_img[:, :height, :width] = v_img.permute(2, 0, 1)
        g_alpha = torch.zeros(rows, stride)
        if v_alpha is not None:
            g_alpha[:height, :width] = v_alpha
        det = deterministic(rt, defines)
        variant = kernel_variant(C, defines)
        if det:  # the kernels test #ifdef, so the define is present only when on
            variant["DETERMINISTIC"] = 1
        elif rt.float_atomics:  # cl_ext_float_atomics instead of the compare-and-swap loop
            variant["USE_FLOAT_ATOMICS"] = 1
        src, _ = raster_variant(rt)
        local, variant = fit_variant(rt, src, "rasterize_bwd", variant)
        # Deterministic: each tile writes its share of each splat's gradient to the splat's pair
        # slot, then reduce.cl sums the slots in a fixed order. Otherwise atomics add into zeros.
        outs = [rt.empty(n, 2), rt.empty(n, 3), rt.empty(n), rt.empty(n, C)] if det else [
            torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, C)]  # fmt: skip
        contrib = rt.scratch(bins.ids.numel() if det else 1, 6 + C)
        if bins.ids.numel():
            # atomics: the projection's backward reads the sums next (deterministic: reduce.cl's)
            a_outs = [rt.array(t, "scratch" if det else "acc", keep=True) for t in outs]
            kept = [rt.reuse(t, b) for t, b in zip(ctx.saved_tensors, ctx.bufs, strict=True)]
            a_m2, a_con, a_op, a_ft, a_bg, a_t, a_last = kept
            a_bins = bins.arrays(rt, "tile_start", "tile_end", "ids")
            rt.run(
                src, "rasterize_bwd", (bins.n_tiles * local,), (local,),
                [i32(bins.tiles_x), i32(stride), i32(plane), *a_bins,
                 a_m2, a_con, a_op, *bins.arrays(rt, "extents"), a_ft, a_bg, a_t, a_last, g_img, g_alpha,
                 (torch.empty(C, rows, stride), "scratch"), contrib,
                 # deterministic: the kernel writes `contrib`, not these (reduce.cl does)
                 *a_outs],
                defines=variant,
                wait=not det,  # the reduction reads `contrib` next on the same in-order queue
            )  # fmt: skip
        if det:
            reduce_pair_grads(rt, bins, contrib, outs, C)
        v_bg = None
        if has_bg:
            v_bg = (g_img * t_final).sum(dim=(1, 2)).to(dtype)
        v_m2, v_con, v_op, v_ft = (o.to(dtype) for o in outs)
        return v_m2, v_con, v_op, v_ft, None, None, None, v_bg, None, None, None


def rasterize_to_pixels(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    stats: dict | None = None,
    device: Runtime | str | None = None,
    bins: TileBins | None = None,
    defines: dict[str, Any] | None = None,
) -> tuple[Tensor, Tensor]:
    """OpenCL twin of `coin_cl.engine.reference.rasterize_to_pixels` (same arguments and outputs).

    `bins` reuses a `bin_tiles` result of the same splats (another pass over the same view);
    by default the splats are binned here. `defines` overrides build-time knobs
    (ALPHA_THRESHOLD, TRANSMITTANCE_MIN, ACC_DOUBLE, ...) for error-against-time studies; the
    defaults are the reference semantics.
    """
    C = features.shape[1]
    if not 1 <= C <= cst.MAX_CHANNELS:
        raise ValueError(f"features has {C} channels; 1 to {cst.MAX_CHANNELS} are supported")
    rt = resolve_device(device)
    width, height = int(width), int(height)
    if bins is None:
        bins = bin_tiles(means2d, conics, opacities, depths, radii, width, height, max_pairs, device=rt)
    return _Rasterize.apply(
        means2d, conics, opacities, features, bins, width, height, background, stats, rt, dict(defines or {})
    )
