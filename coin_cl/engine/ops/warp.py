"""Reprojection-based feature warping (CoIn paper 4.3, "GS-based reference feature warping").

A point cloud P (the reference view's rendered depth unprojected, restricted by the caller to a
margin around the mask) carries a source view's feature image into a target view (the
intermediate camera phi of `coin_cl.scene.conventions.interpolate_pose`). kernels/warp.cl;
the float64 twin is `coin_cl.engine.reference_warp`:

1. each point is projected into the source camera; dropped when non-finite, at z <= 0, outside
   [0, W) x [0, H), or (when `src_depth` is given) occluded there: its camera z exceeds the
   source depth at the pixel holding it by more than the relative `src_depth_tol`
   (z > d (1 + tol); pixels with depth <= 0 or non-finite count as empty, nothing occludes);
2. its feature is gathered bilinearly (pixel centres at +0.5, corners clamped to the image);
3. it is projected into the target camera; dropped at z <= 0 or outside [0, W') x [0, H');
4. splat with a z-buffer. Footprint "bilinear" (default): the 2x2 target pixel centres around
   the projection with bilinear weights; "nearest": the pixel holding it, weight 1. A point is a
   candidate of every footprint pixel with positive weight; per pixel, zmin is the nearest
   candidate's camera z and the winners are the candidates with z <= zmin (1 + depth_tol)
   (relative, so the warp is scale invariant). Outputs per target pixel: the winners' feature
   mean weighted by footprint weights, their weight sum (coverage; 0 = no correspondence) and
   zmin (0 where no candidate).

Only dropped points are excluded: nothing else of the target is touched beyond writing the
outputs of tiles that receive no point (zeros). Gradients flow to `src_features` only (the
gather's adjoint); points, cameras and depth get none.

Determinism: no atomics anywhere. Points are binned to 16x16 tiles of the target (forward) and of
the source (backward) by per-chunk counting and an exclusive scan, so each tile's list is in
point-id order; one work-item per tile owns its pixels and walks its list in that order. The
backward is therefore bit-reproducible, run after run, on any device.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.ops._util import f32, groups, i32
from coin_cl.engine.runtime import Runtime, as_f32, resolve_device
from coin_cl.engine.warp_spec import FOOTPRINTS, STATUS, camera_vector, check_inputs


class _Bins:
    """Point ids per 16x16 tile, each list in id order: ids[tile_start[t]:tile_end[t]]."""

    def __init__(self, rt: Runtime, rects: Tensor, a_rects, tiles_x: int, tiles_y: int):
        n_tiles = tiles_x * tiles_y
        m = rects.shape[0]
        self.tile_start = torch.zeros(n_tiles, dtype=torch.int32)
        self.tile_end = torch.zeros(n_tiles, dtype=torch.int32)
        self.ids = torch.zeros(0, dtype=torch.int32)
        area = (rects[:, 2] - rects[:, 0]).to(torch.int64) * (rects[:, 3] - rects[:, 1])
        n_pairs = int(area.sum()) if m else 0
        self.n_pairs = n_pairs
        if n_pairs == 0:
            return
        # Chunks of consecutive points: enough to keep every compute unit busy, few enough that the
        # [chunks, tiles] histogram stays small (as kernels/bin.cl does for the rasterizer).
        n_chunks = int(min(m, max(1, min(1024, (1 << 22) // n_tiles, m // 256 + 1))))
        chunk = (m + n_chunks - 1) // n_chunks
        n_chunks = (m + chunk - 1) // chunk
        hist = torch.zeros(n_chunks, n_tiles, dtype=torch.int32)
        a_hist = rt.array(hist, mode="acc")
        rt.launch("warp.cl", "warp_bin_count", (n_chunks,), None, i32(m), i32(chunk), i32(n_tiles),
                  i32(tiles_x), a_rects.buf, a_hist.buf, defines=_BIN_DEFINES)  # fmt: skip
        rt.finish(a_hist)
        counts = hist.t().reshape(-1)  # tile-major
        offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).contiguous()
        self.tile_start = offsets.view(n_tiles, n_chunks)[:, 0].clone()
        self.tile_end = torch.cat([self.tile_start[1:], torch.tensor([n_pairs], dtype=torch.int32)])
        self.ids = rt.empty(n_pairs, dtype=torch.int32)
        a_off, a_ids = rt.array(offsets), rt.array(self.ids, mode="out")  # offsets: consumed in place
        rt.launch("warp.cl", "warp_bin_scatter", (n_chunks,), None, i32(m), i32(chunk), i32(n_chunks),
                  i32(tiles_x), a_rects.buf, a_off.buf, a_ids.buf, defines=_BIN_DEFINES)  # fmt: skip
        rt.finish(a_ids)


# The binning kernels do not depend on the channel count or footprint: one build serves all.
_BIN_DEFINES = {"NUM_CHANNELS": 1, "FOOTPRINT": 1}


def _tiles(w: int, h: int) -> tuple[int, int]:
    return math.ceil(w / cst.TILE_SIZE), math.ceil(h / cst.TILE_SIZE)


class _Warp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, src_features, src_cam, dst_cam, src_depth, dst_w, dst_h, depth_tol,
                src_depth_tol, footprint, stats, rt):  # fmt: skip
        m = points.shape[0]
        sh, sw, C = src_features.shape
        pts, feat = as_f32(points), as_f32(src_features)
        depth_in = as_f32(src_depth) if src_depth is not None else torch.zeros(1)
        defines = {"NUM_CHANNELS": C, "FOOTPRINT": FOOTPRINTS[footprint]}
        status = rt.empty(m, dtype=torch.int32)
        src_uv, dst_uvz = rt.empty(m, 2), rt.empty(m, 4)
        src_rect, dst_rect = rt.empty(m, 4, dtype=torch.int32), rt.empty(m, 4, dtype=torch.int32)
        a_pt_out = [rt.array(t, mode="out") for t in (status, src_uv, dst_uvz, src_rect, dst_rect)]
        if m:
            a_in = [rt.array(t) for t in (pts, src_cam, dst_cam)]
            rt.launch("warp.cl", "warp_points", (groups(m),), (64,), i32(m), *[a.buf for a in a_in],
                      i32(sw), i32(sh), i32(dst_w), i32(dst_h), rt.array(depth_in).buf,
                      i32(src_depth is not None), f32(src_depth_tol), *[a.buf for a in a_pt_out],
                      defines=defines)  # fmt: skip
            rt.finish(*a_pt_out)
        a_status, a_suv, a_duvz, a_srect, a_drect = a_pt_out
        tx, ty = _tiles(dst_w, dst_h)
        bins = _Bins(rt, dst_rect, a_drect, tx, ty)
        out = rt.empty(dst_h, dst_w, C)
        weight, depth = rt.empty(dst_h, dst_w), rt.empty(dst_h, dst_w)
        a_out = [rt.array(t, mode="out") for t in (out, weight, depth)]
        a_bins = [rt.array(t) for t in (bins.tile_start, bins.tile_end, bins.ids)]
        a_feat = rt.array(feat)
        rt.launch("warp.cl", "warp_splat", (tx * ty,), None, i32(tx), i32(dst_w), i32(dst_h),
                  *[a.buf for a in a_bins], a_suv.buf, a_duvz.buf, a_feat.buf, i32(sw), i32(sh),
                  f32(depth_tol), *[a.buf for a in a_out], defines=defines)  # fmt: skip
        rt.finish(*a_out)
        if stats is not None:
            counts = torch.bincount(status.long(), minlength=len(STATUS)) if m else torch.zeros(len(STATUS))
            stats.update({f"n_{s}": int(c) for s, c in zip(STATUS, counts.tolist())})
            stats.update(n_points=m, n_pairs=bins.n_pairs, status=status)
        ctx.save_for_backward(src_uv, dst_uvz, src_rect, weight, depth)
        ctx.meta = (rt, defines, sw, sh, dst_w, dst_h, depth_tol, src_features.dtype)
        ctx.mark_non_differentiable(weight, depth)
        return out.to(src_features.dtype), weight.to(src_features.dtype), depth.to(src_features.dtype)

    @staticmethod
    def backward(ctx, v_out, _v_weight, _v_depth):
        src_uv, dst_uvz, src_rect, weight, depth = ctx.saved_tensors
        rt, defines, sw, sh, dst_w, dst_h, depth_tol, dtype = ctx.meta
        C = defines["NUM_CHANNELS"]
        v_src = rt.empty(sh, sw, C)
        g = as_f32(v_out) if v_out is not None else torch.zeros(dst_h, dst_w, C)
        tx, ty = _tiles(sw, sh)
        a_srect = rt.array(src_rect)
        bins = _Bins(rt, src_rect, a_srect, tx, ty)
        a_in = [rt.array(t) for t in (bins.tile_start, bins.tile_end, bins.ids, src_uv, dst_uvz)]
        a_z = [rt.array(t) for t in (depth, weight, g)]
        a_v = rt.array(v_src, mode="out")
        rt.launch("warp.cl", "warp_grad", (tx * ty,), None, i32(tx), i32(sw), i32(sh),
                  *[a.buf for a in a_in], i32(dst_w), i32(dst_h), *[a.buf for a in a_z],
                  f32(depth_tol), a_v.buf, defines=defines)  # fmt: skip
        rt.finish(a_v)
        return None, v_src.to(dtype), None, None, None, None, None, None, None, None, None, None


def warp_features(
    points: Tensor,
    src_K,
    src_viewmat,
    src_features: Tensor,
    dst_K,
    dst_viewmat,
    dst_width: int,
    dst_height: int,
    src_depth: Tensor | None = None,
    depth_tol: float = cst.WARP_DEPTH_TOL,
    src_depth_tol: float = cst.WARP_SRC_DEPTH_TOL,
    footprint: str = "bilinear",
    stats: dict[str, Any] | None = None,
    device: Runtime | str | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Warp a source view's feature image into a target view through a point cloud (see module doc).

    Args:
        points: [M, 3] world points (M may be 0; NaN/Inf rows are dropped and counted).
        src_K, dst_K: [3, 3] intrinsics (numpy or torch; pixel centres at +0.5).
        src_viewmat, dst_viewmat: [4, 4] world-to-camera, OpenCV axes (numpy or torch).
        src_features: [H, W, C] source features, 1 <= C <= 128 (differentiable).
        dst_width, dst_height: target image size W' x H' (>= 1).
        src_depth: optional [H, W] camera z of the source's rendered surface (occlusion test).
        depth_tol: relative z-buffer tolerance (winners: z <= zmin (1 + depth_tol)).
        src_depth_tol: relative source occlusion tolerance (occluded: z > d (1 + src_depth_tol)).
        footprint: "bilinear" (2x2 pixel centres, bilinear weights) or "nearest" (one pixel).
        stats: if a dict, filled with n_points, n_pairs, per-status counts n_ok, n_nonfinite,
            n_behind_src, n_outside_src, n_occluded_src, n_behind_dst, n_outside_dst, and
            `status` [M] int32 (codes index `STATUS`).
        device: the OpenCL device (a `Runtime`, a name substring, or None for the default).
    Returns:
        features [H', W', C] (dtype of src_features), weight [H', W'] (sum of the winners'
        footprint weights; > 0 exactly where a correspondence exists), depth [H', W'] (z-buffer:
        the nearest candidate's camera z, 0 where none). Only `features` is differentiable.
    """
    dst_width, dst_height = int(dst_width), int(dst_height)
    check_inputs(points, src_features, dst_width, dst_height, src_depth, depth_tol, src_depth_tol, footprint)
    src_cam = camera_vector(src_K, src_viewmat, "source camera")
    dst_cam = camera_vector(dst_K, dst_viewmat, "target camera")
    rt = resolve_device(device)
    sd = None if src_depth is None else src_depth.detach()
    return _Warp.apply(points.detach(), src_features, src_cam, dst_cam, sd, dst_width, dst_height,
                       float(depth_tol), float(src_depth_tol), footprint, stats, rt)  # fmt: skip


def support_mask(weight: Tensor, mask: Tensor) -> Tensor:
    """The point-cloud support mask m^P_n (paper 4.3): pixels of view n inside its inpainting mask
    that received a valid correspondence through P.

    Args:
        weight: [H, W] coverage from `warp_features(P, reference camera, ..., view n's camera)`,
            i.e. warped INTO view n: > 0 where some point of P, visible in the reference view, is a
            z-buffer winner in view n.
        mask: [H, W] bool inpainting mask of view n (True = region to inpaint).
    Returns:
        [H, W] bool, mask & (weight > 0).
    """
    if tuple(weight.shape) != tuple(mask.shape):
        raise ValueError(f"weight {tuple(weight.shape)} and mask {tuple(mask.shape)} differ in shape")
    return mask.to(torch.bool) & (weight > 0)
