"""torch.autograd Functions that launch the OpenCL kernels; same signatures as `coin_cl.reference`.

Everything crosses into the kernels as contiguous float32 / int32 tensors wrapped by the runtime
(aliased on unified-memory devices, copied and counted elsewhere).
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl import constants as cst
from coin_cl.reference import PairOverflowError
from coin_cl.runtime import Runtime, as_f32, get_runtime

i32 = np.int32
f32 = np.float32


def _cam(viewmat: Tensor, K: Tensor) -> Tensor:
    v = viewmat.detach().to(torch.float32)
    k = K.detach().to(torch.float32)
    return torch.cat([v[:3, :3].reshape(-1), v[:3, 3], torch.stack([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])])


def _groups(n: int, local: int = 64) -> int:
    return max(local, (n + local - 1) // local * local)


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far, rt):
        n = means.shape[0]
        cam = _cam(viewmat, K)
        ins = [as_f32(means), as_f32(quats), as_f32(scales), cam]
        means2d, conics, depths = rt.empty(n, 2), rt.empty(n, 3), rt.empty(n)
        radii = rt.empty(n, dtype=torch.int32)
        if n:
            a_in = [rt.array(t) for t in ins]
            a_out = [rt.array(t, mode="out") for t in (means2d, conics, depths, radii)]
            rt.launch(
                "project.cl",
                "project_fwd",
                (_groups(n),),
                (64,),
                i32(n),
                *[a.buf for a in a_in],
                i32(width),
                i32(height),
                f32(near),
                f32(far),
                *[a.buf for a in a_out],
            )
            rt.finish(*a_out)
        ctx.save_for_backward(*ins, radii, conics)
        ctx.meta = (width, height, near, far, rt, means.dtype)
        ctx.mark_non_differentiable(radii)
        return means2d.to(means.dtype), conics.to(means.dtype), depths.to(means.dtype), radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        means, quats, scales, cam, radii, conics = ctx.saved_tensors
        width, height, near, far, rt, dtype = ctx.meta
        n = means.shape[0]
        outs = [rt.empty(n, 3), rt.empty(n, 4), rt.empty(n, 3)]
        if n:
            grads = [
                as_f32(_zero_if_none(g, ref))
                for g, ref in ((v_means2d, (n, 2)), (v_conics, (n, 3)), (v_depths, (n,)))
            ]
            a_in = [rt.array(t) for t in (means, quats, scales, cam, radii, conics, *grads)]
            a_out = [rt.array(t, mode="out") for t in outs]
            rt.launch(
                "project.cl",
                "project_bwd",
                (_groups(n),),
                (64,),
                i32(n),
                *[a.buf for a in a_in[:4]],
                i32(width),
                i32(height),
                f32(near),
                f32(far),
                *[a.buf for a in a_in[4:]],
                *[a.buf for a in a_out],
            )
            rt.finish(*a_out)
        v_means, v_quats, v_scales = (o.to(dtype) for o in outs)
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None


def _zero_if_none(g: Tensor | None, shape: tuple[int, ...]) -> Tensor:
    return torch.zeros(shape) if g is None else g


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = cst.NEAR_PLANE,
    far: float = cst.FAR_PLANE,
    runtime: Runtime | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """OpenCL twin of `coin_cl.reference.project` (same arguments and outputs)."""
    rt = runtime or get_runtime()
    return _Project.apply(means, quats, scales, viewmat, K, int(width), int(height), near, far, rt)


class TileBins:
    """Depth-ordered splat ids per tile: ids[tile_start[t]:tile_end[t]] for tile t."""

    def __init__(self, rt: Runtime, means2d, conics, opacities, depths, radii, width, height, max_pairs):
        ts = cst.TILE_SIZE
        self.tiles_x, self.tiles_y = math.ceil(width / ts), math.ceil(height / ts)
        n_tiles = self.tiles_x * self.tiles_y
        n = means2d.shape[0]
        # Per-splat half extents (px) of the opacity-aware box; read by the rasterizers.
        self.extents = rt.empty(n, 2)
        self.tile_start = torch.zeros(n_tiles, dtype=torch.int32)
        self.tile_end = torch.zeros(n_tiles, dtype=torch.int32)
        self.ids = torch.zeros(0, dtype=torch.int32)
        # pair_slot[pair_start[g]:pair_start[g + 1]]: where splat g's (tile, splat) pairs are in ids
        self.pair_start = torch.zeros(n + 1, dtype=torch.int32)
        self.pair_slot = torch.zeros(0, dtype=torch.int32)
        self.n_pairs = self.n_visible = 0
        if n == 0:
            return
        rects = rt.empty(n, 4, dtype=torch.int32)
        a_m, a_c, a_o, a_r = (rt.array(t) for t in (means2d, conics, opacities, radii))
        a_rects = rt.array(rects, mode="out")
        a_ext = rt.array(self.extents, mode="out")
        rt.launch(
            "bin.cl",
            "bin_rects",
            (_groups(n),),
            (64,),
            i32(n),
            a_m.buf,
            a_c.buf,
            a_o.buf,
            a_r.buf,
            i32(self.tiles_x),
            i32(self.tiles_y),
            a_rects.buf,
            a_ext.buf,
        )
        rt.finish(a_rects, a_ext)
        area = (rects[:, 2] - rects[:, 0]).to(torch.int64) * (rects[:, 3] - rects[:, 1])
        n_pairs = int(area.sum())
        # Checked before anything pair-sized is allocated: a clear error, never an OOM.
        if n_pairs > max_pairs:
            raise PairOverflowError(n_pairs, max_pairs)
        self.n_pairs = n_pairs
        if n_pairs == 0:
            return
        self.pair_start[1:] = torch.cumsum(area, 0)
        # One stable depth sort of the splats that reach a tile; every tile list inherits it.
        vis = (area > 0).nonzero().squeeze(1)
        order_np = np.argsort(depths[vis].numpy(), kind="stable")  # numpy's beats torch's here
        order = vis[torch.from_numpy(order_np)].to(torch.int32)
        n_vis = self.n_visible = int(order.numel())
        rects = rects[order.long()]  # gathered once, so the passes below read sequentially
        a_rects, a_order = rt.array(rects), rt.array(order)
        # Enough chunks to keep every compute unit busy with some balance, few enough that the
        # [chunks, tiles] histogram stays small.
        n_chunks = int(min(n_vis, max(1, min(1024, (1 << 22) // n_tiles, n_vis // 256 + 1))))
        chunk = (n_vis + n_chunks - 1) // n_chunks
        n_chunks = (n_vis + chunk - 1) // chunk
        hist = torch.zeros(n_chunks, n_tiles, dtype=torch.int32)
        a_hist = rt.array(hist, mode="inout")
        rt.launch(
            "bin.cl",
            "bin_count",
            (n_chunks,),
            None,
            i32(n_vis),
            i32(chunk),
            i32(n_tiles),
            i32(self.tiles_x),
            a_rects.buf,
            a_hist.buf,
        )
        rt.finish(a_hist)
        counts = hist.t().reshape(-1)  # tile-major
        offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).contiguous()
        per_tile = offsets.view(n_tiles, n_chunks)[:, 0].clone()
        self.tile_start = per_tile
        self.tile_end = torch.cat([per_tile[1:], torch.tensor([n_pairs], dtype=torch.int32)])
        self.ids = rt.empty(n_pairs, dtype=torch.int32)
        self.pair_slot = rt.empty(n_pairs, dtype=torch.int32)
        a_off, a_start = rt.array(offsets), rt.array(self.pair_start)
        a_ids, a_slot = rt.array(self.ids, mode="out"), rt.array(self.pair_slot, mode="out")
        rt.launch(
            "bin.cl",
            "bin_scatter",
            (n_chunks,),
            None,
            i32(n_vis),
            i32(chunk),
            i32(n_chunks),
            i32(self.tiles_x),
            a_rects.buf,
            a_order.buf,
            a_off.buf,
            a_start.buf,
            a_ids.buf,
            a_slot.buf,
        )
        rt.finish(a_ids, a_slot)


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


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        features,
        depths,
        radii,
        width,
        height,
        background,
        max_pairs,
        stats,
        rt,
        defines,
    ):
        C = features.shape[1]
        m2, con, op, ft = (as_f32(t) for t in (means2d, conics, opacities, features))
        bg = torch.zeros(C) if background is None else as_f32(background)
        radii = radii.to(torch.int32).contiguous()
        bins = TileBins(rt, m2, con, op, depths.detach(), radii, width, height, max_pairs)
        ts = cst.TILE_SIZE
        stride, rows = bins.tiles_x * ts, bins.tiles_y * ts
        plane = stride * rows
        n_tiles = bins.tiles_x * bins.tiles_y
        img, t_final = rt.empty(C, rows, stride), rt.empty(rows, stride)
        last = rt.empty(rows, stride, dtype=torch.int32)
        variant = kernel_variant(C, defines)
        src, local = raster_variant(rt)
        a_in = [
            rt.array(t) for t in (bins.tile_start, bins.tile_end, bins.ids, m2, con, op, bins.extents, ft, bg)
        ]
        a_out = [rt.array(t, mode="out") for t in (img, t_final, last)]
        rt.launch(
            src,
            "rasterize_fwd",
            (n_tiles * local,),
            (local,),
            i32(bins.tiles_x),
            i32(stride),
            i32(plane),
            *[a.buf for a in a_in],
            *[a.buf for a in a_out],
            defines=variant,
        )
        rt.finish(*a_out)
        if stats is not None:
            # last: per pixel, how many splats of its tile list were composited (1-based index
            # of the last contributor); the backward pass starts there.
            stats.update(n_pairs=bins.n_pairs, n_visible=bins.n_visible, last=last[:height, :width])
        ctx.save_for_backward(
            m2, con, op, bins.extents, ft, bg, bins.tile_start, bins.tile_end, bins.ids, t_final, last,
            bins.pair_start, bins.pair_slot,
        )  # fmt: skip
        ctx.meta = (width, height, rt, defines, bins.tiles_x, features.dtype, background is not None)
        out_img = img[:, :height, :width].permute(1, 2, 0).to(features.dtype)
        out_alpha = (1.0 - t_final[:height, :width]).to(features.dtype)
        return out_img, out_alpha

    @staticmethod
    def backward(ctx, v_img, v_alpha):
        m2, con, op, ext, ft, bg, tstart, tend, ids, t_final, last, pair_start, pair_slot = ctx.saved_tensors
        width, height, rt, defines, tiles_x, dtype, has_bg = ctx.meta
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
        src, local = raster_variant(rt)
        nq = 6 + C
        # Deterministic: each tile writes its share of each splat's gradient to the splat's pair
        # slot, then reduce.cl sums the slots in a fixed order. Otherwise atomics add into zeros.
        outs = [rt.empty(n, 2), rt.empty(n, 3), rt.empty(n), rt.empty(n, C)] if det else [
            torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, C)]  # fmt: skip
        contrib = rt.empty(ids.numel() if det else 1, nq)
        a_in = [
            rt.array(t) for t in (tstart, tend, ids, m2, con, op, ext, ft, bg, t_final, last, g_img, g_alpha)
        ]
        a_scr = rt.array(rt.empty(C, rows, stride), mode="scratch")
        a_contrib = rt.array(contrib, mode="scratch")
        a_out = [rt.array(t, mode="out" if det else "inout") for t in outs]
        if ids.numel():
            rt.launch(
                src,
                "rasterize_bwd",
                (tstart.numel() * local,),
                (local,),
                i32(tiles_x),
                i32(stride),
                i32(plane),
                *[a.buf for a in a_in],
                a_scr.buf,
                a_contrib.buf,
                *[a.buf for a in a_out],
                defines=variant,
            )
        if det and n:
            a_start, a_slot = rt.array(pair_start), rt.array(pair_slot)
            rt.launch(
                "reduce.cl",
                "reduce_grads",
                (_groups(n),),
                (64,),
                i32(n),
                a_start.buf,
                a_slot.buf,
                a_contrib.buf,
                *[a.buf for a in a_out],
                defines={"NUM_CHANNELS": C},
            )
        rt.finish(*a_out)
        v_bg = None
        if has_bg:
            v_bg = (g_img * t_final).sum(dim=(1, 2)).to(dtype)
        v_m2, v_con, v_op, v_ft = (o.to(dtype) for o in outs)
        return v_m2, v_con, v_op, v_ft, None, None, None, None, v_bg, None, None, None, None


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
    runtime: Runtime | None = None,
    defines: dict[str, Any] | None = None,
) -> tuple[Tensor, Tensor]:
    """OpenCL twin of `coin_cl.reference.rasterize_to_pixels` (same arguments and outputs).

    `defines` overrides build-time knobs (ALPHA_THRESHOLD, TRANSMITTANCE_MIN, ACC_DOUBLE) for
    error-against-time studies; the defaults are the reference semantics.
    """
    C = features.shape[1]
    if not 1 <= C <= cst.MAX_CHANNELS:
        raise ValueError(f"features has {C} channels; 1 to {cst.MAX_CHANNELS} are supported")
    rt = runtime or get_runtime()
    return _Rasterize.apply(
        means2d,
        conics,
        opacities,
        features,
        depths,
        radii,
        int(width),
        int(height),
        background,
        max_pairs,
        stats,
        rt,
        dict(defines or {}),
    )
