"""Stage 3, Consistency Loss Guidance (CLG, paper 4.3): re-inpaint every non-reference view with the
diffusion sampler steered toward 3D consistency with the reference view k.

For each view n (not k, non-empty mask; other views are skipped and logged) the sampler of
`coin_cl.diffusion` runs on a square crop around the mask (the same crop rule as stage 1,
`diffusion.inpaint2d.crop_box`), resized to the model's working size (64 for the scene prior, 512
for Stable Diffusion 2), with FreeDoM energy guidance on the decoded x0 prediction X.

Geometry. Everything is evaluated at the sampler's resolution: a crop and a resize are a change of
intrinsics, K' = diag(s, s, 1) (K - [0 0 x0; 0 0 y0; 0 0 0]) with s = work / side (pixel centres
at +0.5, so this matches cv2's area/cubic resizes exactly), so the warp op sees three small cameras:
- view n's crop camera (the sampler's own pixels);
- the reference's crop camera at the same scale s around the bounding box of P_k in view k;
- the intermediate camera phi = `interpolate_pose(V_k, V_n, alpha)` with intrinsics
  (1 - alpha) K_k + alpha K_n, cropped to the bounding box of P_k's projections (phi is virtual:
  it has no image border), at the same scale s.

Energy (paper eq. "E(X) = m L3D + (1 - m) ||X - R_n||_1"; the terms live in different images, so
this is the precise form used). With H the hole (view n's mask at working size) and
S = `support_mask(weight of warp(P_k: k -> n), H)` the point-cloud support m^P_n in view n:

    E(X) = ( |S| * L3D(X) + sum_{p in H \\ S} mean_c |X(p) - R_n(p)| ) / |H|

    L3D(X) = mean over V of [ w_hr (1 - cos(Fk_hr, Fn_hr)) + w_rgb ||Fk_rgb - Fn_rgb||_2^2 ]

where Fk = warp(f(I^_k): k -> phi), Fn = warp(f(X~): n -> phi), f = [f_hr, rgb] (the feature
extractor's channels and the image itself), X~ = X inside H and I^_n outside (what the output will
be after compositing: features have spatial support, so the known surroundings must be there),
and V = the phi pixels where both warps have a correspondence (weight > 0). So supported mask
pixels pull X toward the reference through the geometry, the rest toward the GS render R_n, each in
proportion to its share of the hole (the paper's per-pixel m / (1 - m) weighting averaged over the
hole; L3D lives at phi, not in view n, so it enters as its mean). Source depths, when given, drive
the warp's occlusion test in k and n.

Output: the last step's decoded x0 prediction, clamped, resized back to the crop and pasted into
I^_n inside the mask only (`diffusion.inpaint2d.paste`, feathered inward), so every pixel outside
the mask is bit-identical to I^_n; written as `images/<stem>.png` with `views/<stem>.json` (figures).
A view whose PNG exists is not redone (resume). Randomness: view n samples with seed + n.

Before Ref-GS exists, `reference_points` builds P_k from any depth map of the reference view (GS
render, ground truth, ...) with the same margin rule as the Ref-GS stage.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from coin_cl.diffusion.inpaint2d import crop_box, paste
from coin_cl.diffusion.sampling import DDIMSampler, Denoiser, SamplerConfig
from coin_cl.scene.conventions import interpolate_pose
from coin_cl.scene.io import atomic_write, to_uint8, write_png

log = logging.getLogger(__name__)

PAPER_STEPS = 200  # paper 4.3 / supplement: 200 'quad' DDIM steps with Stable Diffusion 2
PRIOR_STEPS = 25  # the scene prior: a small pixel-space UNet on 2 cores, where 200 steps cost minutes a view
MAX_WARP_CHANNELS = 128  # the warp op's channel limit (engine constants.MAX_CHANNELS); DINO is chunked
MIN_FEATURE_SIDE = 32  # feature images must exceed the analytic extractor's reflect padding (14 px)


@dataclass
class CLGConfig:
    """Settings of the CLG stage.

    steps: DDIM steps; None = PAPER_STEPS (200) for Stable Diffusion 2, PRIOR_STEPS (25) for the
        scene prior (the named smaller default: 200 steps of the prior cost minutes per view here).
    discretization: 'quad' (paper) or 'uniform'. eta: DDIM stochasticity (0 = deterministic).
    guidance_scale: FreeDoM's c (the energy step is c x the size of the DDIM update); 0 = unguided.
    guidance_start, guidance_end: the guided part of the trajectory (fractions, 0 = noisiest step);
        the last steps only sharpen, guiding them fights the model for little consistency.
    travel_repeats, travel_start, travel_end: FreeDoM time travel (1 = off; each repeat costs a step).
    cfg_scale: classifier-free guidance (SD2 with a prompt only). prompt: text (SD2 only).
    alpha: position of the intermediate pose phi between k (0) and n (1) (paper 0.5).
    context: crop side >= context x the mask's bounding box side (as stage 1).
    w_hr, w_rgb: weights of the cosine and RGB terms of L3D (paper: 1 and 1).
    depth_tol, src_depth_tol, footprint: the warp op's knobs (see `coin_cl.engine.warp_features`).
    max_points: P_k is thinned to at most this many points (evenly by index) for speed; at the
        sampler's scale many points share a pixel anyway.
    feather_px: inward feather of the paste (outside the mask is untouched either way).
    seed: view n samples with seed + n. progress: tqdm bars over views and steps.
    sample: False = no diffusion sampler: every hole pixel takes the energy's own target, the
        reference's colour warped through P_k where supported (S) and R_n elsewhere, i.e. the
        minimiser of E(X) with the RGB term alone (`warp_fill`). The pipeline uses it for an
        edited reference (`coin_cl.pipeline.insert`), where no model can draw the inserted object
        and a sampler would paint the hole with the scene's own textures.
    """

    steps: int | None = None
    discretization: str = "quad"
    eta: float = 0.0
    guidance_scale: float = 0.5
    guidance_start: float = 0.0
    guidance_end: float = 0.8
    travel_repeats: int = 1
    travel_start: float = 0.2
    travel_end: float = 0.5
    cfg_scale: float = 1.0
    prompt: str = ""
    alpha: float = 0.5
    context: float = 1.5
    w_hr: float = 1.0
    w_rgb: float = 1.0
    depth_tol: float = 0.01
    src_depth_tol: float = 0.01
    footprint: str = "bilinear"
    max_points: int = 400_000
    feather_px: int = 2
    seed: int = 0
    progress: bool = True
    sample: bool = True

    def num_steps(self, denoiser: Denoiser) -> int:
        if self.steps is not None:
            return int(self.steps)
        return PRIOR_STEPS if getattr(denoiser, "name", "") == "scene prior" else PAPER_STEPS

    def sampler(self, denoiser: Denoiser, guided: bool = True) -> SamplerConfig:
        return SamplerConfig(
            num_steps=self.num_steps(denoiser),
            discretization=self.discretization,
            eta=self.eta,
            cfg_scale=self.cfg_scale,
            guidance_scale=self.guidance_scale if guided else 0.0,
            guidance_start=self.guidance_start,
            guidance_end=self.guidance_end,
            travel_repeats=self.travel_repeats,
            travel_start=self.travel_start,
            travel_end=self.travel_end,
        )


# ----------------------------------------------------------------------------------------------------
# P_k and small geometry helpers


def pk_margin_px(mask: np.ndarray) -> int:
    """Margin around the mask kept in P_k: max(4, 10 % of the bounding box's larger side) px (the
    Ref-GS stage's rule, repeated here so the two agree before that stage lands)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 4
    ys, xs = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return int(max(4, round(0.1 * max(ys[-1] - ys[0] + 1, xs[-1] - xs[0] + 1))))


def reference_points(
    camera: Any,
    depth: np.ndarray,
    mask: np.ndarray,
    margin_px: int | None = None,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """P_k from a depth map of the reference view: its pixels inside the mask dilated by margin_px
    (default `pk_margin_px`), unprojected at their pixel centres (+0.5) to world points.

    Args:
        camera: the reference `Camera` (K, viewmat, width, height).
        depth: [H, W] camera z (a GS render, ground truth, ...); pixels with non-finite or <= 0
            depth are left out.
        mask: [H, W] bool inpainting mask of the reference view.
        margin_px: dilation radius in pixels (elliptic kernel), >= 0.
        valid: optional [H, W] bool, e.g. rendered alpha > 0.5 (pixels where the depth means a surface).
    Returns:
        [M, 3] float32 world points, row-major pixel order (M may be 0).
    """
    depth = np.asarray(depth, dtype=np.float64)
    mask = np.asarray(mask, bool)
    H, W = int(camera.height), int(camera.width)
    if depth.shape != (H, W) or mask.shape != (H, W):
        raise ValueError(f"depth {depth.shape} and mask {mask.shape} must be the camera's ({H}, {W})")
    if valid is not None and np.shape(valid) != (H, W):
        raise ValueError(f"valid has shape {np.shape(valid)}, expected ({H}, {W})")
    m = pk_margin_px(mask) if margin_px is None else int(margin_px)
    if m < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    region = cv2.dilate(mask.astype(np.uint8), ker).astype(bool)
    with np.errstate(invalid="ignore"):
        sel = region & np.isfinite(depth) & (depth > 0)
    if valid is not None:
        sel &= np.asarray(valid, bool)
    ys, xs = np.nonzero(sel)
    uv = np.stack([xs + 0.5, ys + 0.5], 1).astype(np.float64)
    return camera.unproject(uv, depth[ys, xs]).astype(np.float32)


def _crop_K(K: np.ndarray, x0: float, y0: float, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of the image cropped at (x0, y0) then resized by (sx, sy)."""
    Kc = np.array(K, dtype=np.float64, copy=True)
    Kc[0, 2] -= x0
    Kc[1, 2] -= y0
    return np.diag([sx, sy, 1.0]) @ Kc


def _crop(a: np.ndarray, y0: int, x0: int, side_y: int, side_x: int) -> np.ndarray:
    """Crop [y0, y0 + side_y) x [x0, x0 + side_x), reflect-padding what lies outside the image (as
    stage 1 does, so the sampler sees the same context)."""
    H, W = a.shape[:2]
    pt, pl = max(-y0, 0), max(-x0, 0)
    pb, pr = max(y0 + side_y - H, 0), max(x0 + side_x - W, 0)
    if pt or pl or pb or pr:
        a = np.pad(a, [(pt, pb), (pl, pr)] + [(0, 0)] * (a.ndim - 2), mode="symmetric")
    return a[y0 + pt : y0 + pt + side_y, x0 + pl : x0 + pl + side_x]


def _resize(a: np.ndarray, w: int, h: int, nearest: bool = False) -> np.ndarray:
    if a.shape[1] == w and a.shape[0] == h:
        return a
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if a.shape[1] > w else cv2.INTER_CUBIC
    return cv2.resize(a, (w, h), interpolation=interp)


def _project(points: np.ndarray, K: np.ndarray, viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = points.astype(np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    ok = np.isfinite(pc).all(1) & (pc[:, 2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pc[:, :2] / pc[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    return uv, ok & np.isfinite(uv).all(1)


def _depth_t(d: np.ndarray | None) -> torch.Tensor | None:
    if d is None:
        return None
    d = np.where(np.isfinite(d), d, 0.0).astype(np.float32)  # non-finite = empty: nothing occludes
    return torch.from_numpy(np.ascontiguousarray(d))


def _warp(
    points: torch.Tensor,
    src_K: np.ndarray,
    src_V: np.ndarray,
    feats: torch.Tensor,
    dst_K: np.ndarray,
    dst_V: np.ndarray,
    w: int,
    h: int,
    src_depth: torch.Tensor | None,
    cfg: CLGConfig,
    device: Any,
) -> tuple[torch.Tensor, torch.Tensor]:
    """warp_features over channel chunks of at most MAX_WARP_CHANNELS (DINO has 384); returns
    (features [h, w, C], weight [h, w])."""
    from coin_cl.engine import warp_features

    outs, weight = [], None
    for c0 in range(0, feats.shape[-1], MAX_WARP_CHANNELS):
        f, weight, _ = warp_features(
            points, src_K, src_V, feats[..., c0 : c0 + MAX_WARP_CHANNELS].contiguous(), dst_K, dst_V, w, h,
            src_depth=src_depth, depth_tol=cfg.depth_tol, src_depth_tol=cfg.src_depth_tol,
            footprint=cfg.footprint, device=device,
        )  # fmt: skip
        outs.append(f)
    assert weight is not None
    return torch.cat(outs, -1), weight


def _features(extractor: Callable, img: torch.Tensor) -> torch.Tensor:
    """[1, 3, h, w] image -> [h, w, C + 3]: the extractor's channels, then RGB."""
    f = extractor(img)
    if f.dim() != 4 or f.shape[0] != 1 or f.shape[-2:] != img.shape[-2:]:
        raise ValueError(f"feature extractor returned {tuple(f.shape)} for an image {tuple(img.shape)}")
    return torch.cat([f.to(img.dtype), img], 1)[0].permute(1, 2, 0).contiguous()


# ----------------------------------------------------------------------------------------------------
# one view


@dataclass
class _ViewProblem:
    """Everything the energy of one view needs, at the sampler's working size."""

    work: int
    y0: int
    x0: int
    side: int
    image: torch.Tensor  # [1, 3, work, work] I^_n crop
    render: torch.Tensor  # [1, 3, work, work] R_n crop
    hole: torch.Tensor  # [1, 1, work, work] float {0, 1}
    support: torch.Tensor  # [work, work] bool, S = m^P_n
    points: torch.Tensor  # [M, 3] float32
    K_n: np.ndarray
    V_n: np.ndarray
    depth_n: torch.Tensor | None
    K_phi: np.ndarray
    V_phi: np.ndarray
    phi_w: int
    phi_h: int
    ref_warped: torch.Tensor  # [phi_h, phi_w, C + 3]
    ref_weight: torch.Tensor  # [phi_h, phi_w]
    n_hr: int  # channels of f_hr (the rest are RGB)


def _work_size(denoiser: Denoiser) -> int:
    return int(getattr(denoiser, "work_size", 512))


def _setup_view(
    cam_k: Any,
    cam_n: Any,
    inpaint_k: np.ndarray,
    inpaint_n: np.ndarray,
    render_n: np.ndarray,
    depth_k: np.ndarray | None,
    depth_n: np.ndarray | None,
    mask_n: np.ndarray,
    points: np.ndarray,
    extractor: Callable,
    work: int,
    cfg: CLGConfig,
    device: Any,
) -> _ViewProblem:
    H, W = mask_n.shape
    y0, x0, side = crop_box(mask_n, work, cfg.context)
    s = work / side
    img = _resize(_crop(inpaint_n, y0, x0, side, side), work, work)
    ren = _resize(_crop(render_n, y0, x0, side, side), work, work)
    # any coverage of a low-res pixel makes it a hole, as stage 1 (thin mask parts survive downscaling)
    cov = cv2.resize(_crop(mask_n.astype(np.float32), y0, x0, side, side), (work, work),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    hole = cov > 0
    if hole.all():
        raise ValueError("the crop around the mask is entirely masked: nothing to condition on")
    K_n = _crop_K(cam_n.K, x0, y0, s, s)
    d_n = (
        None
        if depth_n is None
        else _resize(_crop(depth_n.astype(np.float32), y0, x0, side, side), work, work, True)
    )

    # the reference's crop: P_k's bounding box in view k (at least MIN_FEATURE_SIDE at scale s)
    uv_k, ok_k = _project(points, cam_k.K, cam_k.viewmat)
    if not ok_k.any():
        raise ValueError("no point of P_k lies in front of the reference camera")
    lo, hi = np.floor(uv_k[ok_k].min(0)) - 2, np.ceil(uv_k[ok_k].max(0)) + 2
    need = math.ceil(MIN_FEATURE_SIDE / s)
    for a in range(2):
        if hi[a] - lo[a] < need:
            c = (hi[a] + lo[a]) / 2
            lo[a], hi[a] = math.floor(c - need / 2), math.floor(c - need / 2) + need
    kx0, ky0 = int(lo[0]), int(lo[1])
    bw, bh = int(hi[0] - lo[0]), int(hi[1] - lo[1])
    rw, rh = max(MIN_FEATURE_SIDE, round(bw * s)), max(MIN_FEATURE_SIDE, round(bh * s))
    K_k = _crop_K(cam_k.K, kx0, ky0, rw / bw, rh / bh)
    ref_img = _resize(_crop(inpaint_k, ky0, kx0, bh, bw), rw, rh)
    d_k = (
        None
        if depth_k is None
        else _resize(_crop(depth_k.astype(np.float32), ky0, kx0, bh, bw), rw, rh, True)
    )

    # the intermediate camera phi, cropped to P_k's projections
    V_phi = np.asarray(interpolate_pose(cam_k.viewmat, cam_n.viewmat, cfg.alpha), dtype=np.float64)
    K_full = (1 - cfg.alpha) * np.asarray(cam_k.K) + cfg.alpha * np.asarray(cam_n.K)
    uv_p, ok_p = _project(points, K_full, V_phi)
    if not ok_p.any():
        raise ValueError("no point of P_k lies in front of the intermediate camera phi")
    plo, phi_hi = np.floor(uv_p[ok_p].min(0)) - 2, np.ceil(uv_p[ok_p].max(0)) + 2
    # phi is virtual (no border), but a huge box means broken geometry: cap it
    cap = 4 * max(H, W)
    plo, phi_hi = np.maximum(plo, -cap), np.minimum(phi_hi, cap)
    K_phi = _crop_K(K_full, plo[0], plo[1], s, s)
    phi_w = max(1, math.ceil((phi_hi[0] - plo[0]) * s))
    phi_h = max(1, math.ceil((phi_hi[1] - plo[1]) * s))

    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    with torch.no_grad():
        fk = _features(extractor, torch.from_numpy(np.ascontiguousarray(ref_img.transpose(2, 0, 1)))[None])
        ref_w, ref_wt = _warp(
            pts, K_k, cam_k.viewmat, fk, K_phi, V_phi, phi_w, phi_h, _depth_t(d_k), cfg, device
        )
        ones = torch.ones(rh, rw, 1)
        _, cov_n = _warp(
            pts, K_k, cam_k.viewmat, ones, K_n, cam_n.viewmat, work, work, _depth_t(d_k), cfg, device
        )
    from coin_cl.engine import support_mask

    hole_t = torch.from_numpy(hole)
    return _ViewProblem(
        work=work, y0=y0, x0=x0, side=side,
        image=torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].float(),
        render=torch.from_numpy(np.ascontiguousarray(ren.transpose(2, 0, 1)))[None].float(),
        hole=hole_t[None, None].float(), support=support_mask(cov_n, hole_t), points=pts,
        K_n=K_n, V_n=np.asarray(cam_n.viewmat, np.float64), depth_n=_depth_t(d_n),
        K_phi=K_phi, V_phi=V_phi, phi_w=phi_w, phi_h=phi_h, ref_warped=ref_w, ref_weight=ref_wt,
        n_hr=fk.shape[-1] - 3,
    )  # fmt: skip


def _make_energy(p: _ViewProblem, extractor: Callable, cfg: CLGConfig, device: Any) -> Callable:
    hole_b = p.hole[0, 0] > 0
    n_hole = max(1, int(hole_b.sum()))
    n_sup = int(p.support.sum())
    unsup = hole_b & ~p.support
    C = p.n_hr

    def energy(x: torch.Tensor) -> torch.Tensor:
        """x: decoded x0 prediction [1, 3, work, work] in about [0, 1] -> scalar energy."""
        if x.shape != p.image.shape:
            raise ValueError(f"decoded image {tuple(x.shape)} is not the working crop {tuple(p.image.shape)}")
        x = x.float()
        xc = p.image * (1 - p.hole) + x * p.hole
        e = x.sum() * 0.0  # keeps the graph even when a term is empty
        if n_sup:
            fn = _features(extractor, xc)
            wn, wt = _warp(
                p.points, p.K_n, p.V_n, fn, p.K_phi, p.V_phi, p.phi_w, p.phi_h, p.depth_n, cfg, device
            )
            valid = (wt > 0) & (p.ref_weight > 0)
            if bool(valid.any()):
                a, b = p.ref_warped[valid], wn[valid]
                cos = F.cosine_similarity(a[:, :C], b[:, :C], dim=1, eps=1e-6)
                l3d = cfg.w_hr * (1 - cos) + cfg.w_rgb * (a[:, C:] - b[:, C:]).pow(2).sum(1)
                e = e + n_sup * l3d.mean()
        if bool(unsup.any()):
            e = e + (x - p.render).abs().mean(1)[0][unsup].sum()
        return e / n_hole

    return energy


def reference_in_view(
    image_k: np.ndarray,
    cam_n: Any,
    cam_k: Any,
    points: np.ndarray,
    depth_k: np.ndarray | None = None,
    device: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The reference image_k (Hk, Wk, 3) warped into view n at full resolution through P_k
    `points` [M, 3] (`warp_features`: k -> n, occlusion-tested against depth_k): (H, W, 3) colours
    and (H, W) weights (0 where no point lands)."""
    from coin_cl.engine import warp_features

    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    with torch.no_grad():
        wk, wt, _ = warp_features(
            pts, cam_k.K, cam_k.viewmat, torch.from_numpy(np.ascontiguousarray(image_k, dtype=np.float32)),
            cam_n.K, cam_n.viewmat, cam_n.width, cam_n.height, src_depth=_depth_t(depth_k), device=device,
        )  # fmt: skip
    return wk.numpy(), wt.numpy()


def consistency_residual(
    image_n: np.ndarray,
    image_k: np.ndarray,
    cam_n: Any,
    cam_k: Any,
    points: np.ndarray,
    mask_n: np.ndarray,
    depth_k: np.ndarray | None = None,
    device: Any = None,
) -> tuple[float, int]:
    """Masked reprojection error of view n to the reference through P_k: the reference image warped
    into view n at full resolution (`warp_features(P_k: k -> n)`), compared inside the support
    mask_n & (weight > 0) as the mean over pixels of the mean absolute RGB difference ([0, 1] units).

    Returns (residual, number of supported pixels); (nan, 0) without support.
    """
    wk, wt = reference_in_view(image_k, cam_n, cam_k, points, depth_k, device)
    sup = np.asarray(mask_n, bool) & (wt > 0)
    n = int(sup.sum())
    if n == 0:
        return float("nan"), 0
    d = np.abs(np.asarray(image_n, np.float32) - wk).mean(-1)
    return float(d[sup].mean()), n


def warp_fill(
    image_n: np.ndarray,
    render_n: np.ndarray,
    image_k: np.ndarray,
    cam_n: Any,
    cam_k: Any,
    points: np.ndarray,
    mask_n: np.ndarray,
    depth_k: np.ndarray | None = None,
    device: Any = None,
) -> tuple[np.ndarray, int]:
    """CLG without a sampler (`CLGConfig.sample` False) for one view: inside mask_n (H, W) bool, the
    reference image_k (Hk, Wk, 3) warped into view n through P_k `points` [M, 3] where supported,
    render_n elsewhere; outside the mask image_n. Returns ((H, W, 3) float32, supported pixels)."""
    wk, wt = reference_in_view(image_k, cam_n, cam_k, points, depth_k, device)
    m = np.asarray(mask_n, bool)
    sup = m & (wt > 0)
    fill = np.where(sup[..., None], wk, render_n)
    return np.where(m[..., None], fill, image_n).astype(np.float32), int(sup.sum())


def _stem(cam: Any, i: int) -> str:
    return Path(cam.name).stem if getattr(cam, "name", "") else f"view_{i:03d}"


def _check_image(a: Any, H: int, W: int, what: str, ch: int | None = 3) -> np.ndarray:
    a = np.asarray(a)
    want = (H, W) if ch is None else (H, W, ch)
    if a.shape != want:
        raise ValueError(f"{what} has shape {a.shape}, expected {want}")
    if ch is not None and not np.isfinite(a).all():
        raise ValueError(f"{what} contains NaN/Inf")
    return a.astype(np.float32, copy=False) if ch is not None else a


def run_clg(
    reference: int,
    views: Sequence[int],
    cameras: Sequence[Any],
    inpaints: Sequence[np.ndarray | None],
    renders: Sequence[np.ndarray | None],
    depths: Sequence[np.ndarray | None] | None,
    masks: Sequence[np.ndarray],
    points: np.ndarray,
    denoiser: Denoiser | None,
    features: Callable | None,
    out_dir: str | Path,
    cfg: CLGConfig | None = None,
    device: Any = None,
) -> dict[str, Any]:
    """Consistency Loss Guidance for `views` against the reference view (see the module docstring).

    Args:
        reference: index k of the reference view (into the per-view sequences).
        views: view indices to process; the reference and views with an empty mask are skipped
            (logged and recorded).
        cameras: per view, a `Camera` (K [3, 3], viewmat [4, 4] world-to-camera, width, height, name).
        inpaints: per view, I^_n [H, W, 3] float in [0, 1] (already composited with the captured
            image outside the mask: it is also the output outside the mask); needed for k and `views`.
        renders: per view, the GS render R_n [H, W, 3] float (the (1 - m) term).
        depths: per view, rendered camera z [H, W] (occlusion tests; non-finite = empty) or None.
        masks: per view, [H, W] bool (True = inpaint).
        points: P_k [M, 3] world points (see `reference_points`); NaN rows are dropped by the warp.
        denoiser: a `coin_cl.diffusion` Denoiser with make_condition (scene prior or SD2); None with
            `cfg.sample` False (as `features`).
        features: f_hr, a differentiable (1, 3, h, w) [0, 1] -> (1, C, h, w) extractor.
        out_dir: writes images/<stem>.png and views/<stem>.json; existing PNGs are kept (resume).
        cfg: `CLGConfig`. device: OpenCL device for the warp (Runtime, name, or None).
    Returns:
        {"views": {stem: record}, "n_guided", "n_skipped", "n_resumed", "steps", "model", ...};
        a record has status 'guided' | 'resumed' | 'skipped' (+ reason) and, when run, the energy
        of I^_n and of the output, the guided steps' energies, the consistency residuals before and
        after, support sizes and seconds.
    """
    from tqdm import tqdm

    cfg = cfg or CLGConfig()
    n_views = len(cameras)
    for name, seq in (("inpaints", inpaints), ("renders", renders), ("masks", masks)):
        if len(seq) != n_views:
            raise ValueError(f"{name} has {len(seq)} entries for {n_views} cameras")
    if depths is not None and len(depths) != n_views:
        raise ValueError(f"depths has {len(depths)} entries for {n_views} cameras")
    if not 0 <= int(reference) < n_views:
        raise ValueError(f"reference view {reference} is not one of the {n_views} views")
    bad = [v for v in views if not 0 <= int(v) < n_views]
    if bad:
        raise ValueError(f"unknown views {bad} (the scene has {n_views})")
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [M, 3], got {points.shape}")
    finite = np.isfinite(points).all(1)
    if not finite.all():
        log.warning("CLG: %d of %d points of P_k are not finite; dropped", int((~finite).sum()), len(points))
        points = points[finite]
    if len(points) > cfg.max_points:
        points = points[np.linspace(0, len(points) - 1, cfg.max_points).round().astype(np.int64)]
    k = int(reference)
    cam_k = cameras[k]
    Hk, Wk = cam_k.height, cam_k.width
    inp_k = _check_image(inpaints[k], Hk, Wk, f"inpaint of the reference view {k}")
    depth_k = (
        None if depths is None or depths[k] is None else _check_image(depths[k], Hk, Wk, "depth k", None)
    )
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "views").mkdir(parents=True, exist_ok=True)
    if cfg.sample and (denoiser is None or features is None):
        raise ValueError(
            "CLG with the sampler needs a denoiser and a feature extractor (or CLGConfig.sample=False)"
        )
    work = _work_size(denoiser) if cfg.sample else 0
    n_steps = cfg.num_steps(denoiser) if cfg.sample else 0
    records: dict[str, dict[str, Any]] = {}
    bar = tqdm(list(views), desc="CLG views", unit="view", disable=not cfg.progress)
    for n in bar:
        n = int(n)
        cam = cameras[n]
        stem = _stem(cam, n)
        bar.set_postfix_str(stem)
        mask = np.asarray(masks[n], bool)
        if n == k:
            records[stem] = {"view": n, "status": "skipped", "reason": "reference view"}
            log.info("CLG: view %d (%s) skipped: the reference view", n, stem)
            continue
        if mask.shape != (cam.height, cam.width):
            raise ValueError(f"mask of view {n} has shape {mask.shape}, expected {(cam.height, cam.width)}")
        if not mask.any():
            records[stem] = {"view": n, "status": "skipped", "reason": "empty mask"}
            log.info("CLG: view %d (%s) skipped: empty mask", n, stem)
            continue
        png, js = out_dir / "images" / f"{stem}.png", out_dir / "views" / f"{stem}.json"
        if png.is_file():
            rec = json.loads(js.read_text()) if js.is_file() else {"view": n}
            records[stem] = rec | {"status": "resumed"}
            log.info("CLG: view %d (%s) already written: kept", n, stem)
            continue
        t0 = time.perf_counter()
        inp_n = _check_image(inpaints[n], cam.height, cam.width, f"inpaint of view {n}")
        if renders[n] is None:
            raise ValueError(f"view {n} has no render R_n")
        ren_n = _check_image(renders[n], cam.height, cam.width, f"render of view {n}")
        depth_n = None if depths is None or depths[n] is None else _check_image(
            depths[n], cam.height, cam.width, f"depth of view {n}", None)  # fmt: skip
        if not cfg.sample:
            out, n_sup = warp_fill(inp_n, ren_n, inp_k, cam, cam_k, points, mask, depth_k, device)
            r_before, _ = consistency_residual(inp_n, inp_k, cam, cam_k, points, mask, depth_k, device)
            written = to_uint8(out).astype(np.float32) / 255
            r_after, _ = consistency_residual(written, inp_k, cam, cam_k, points, mask, depth_k, device)
            rec = {"view": n, "status": "warped", "residual_before": r_before, "residual_after": r_after,
                   "support_px": n_sup, "hole_px": int(mask.sum()),
                   "seconds": time.perf_counter() - t0}  # fmt: skip
            atomic_write(js, lambda p, r=rec: p.write_text(json.dumps(r, indent=1)))
            write_png(png, out)
            records[stem] = rec
            log.info("CLG (warp, no sampler): view %d (%s): %d of %d hole px supported, "
                     "residual %.4f -> %.4f", n, stem, n_sup, int(mask.sum()), r_before, r_after)  # fmt: skip
            continue
        prob = _setup_view(cam_k, cam, inp_k, inp_n, ren_n, depth_k, depth_n, mask, points, features,
                           work, cfg, device)  # fmt: skip
        energy = _make_energy(prob, features, cfg, device)
        cond = denoiser.make_condition(prob.image, prob.hole, cfg.prompt)
        uncond = None
        if cfg.cfg_scale != 1.0 and cfg.prompt and hasattr(denoiser, "encode_prompt"):
            uncond = type(cond)(
                cond.mask, cond.masked_latent, denoiser.encode_prompt("").expand_as(cond.text)
            )
        if hasattr(denoiser, "latent_channels"):  # latent model (SD2): the VAE's grid
            f = int(denoiser.vae_factor)
            shape: tuple[int, ...] = (1, int(denoiser.latent_channels), work // f, work // f)
        else:
            shape = tuple(prob.image.shape)
        g = torch.Generator().manual_seed(cfg.seed + n)
        z = torch.randn(shape, generator=g)
        sbar = tqdm(total=n_steps, desc=f"  {stem} steps", leave=False, disable=not cfg.progress)
        res = DDIMSampler(denoiser, cfg.sampler(denoiser)).sample(
            z, cond, uncond, energy=energy, generator=g, callback=lambda *_, b=sbar: b.update(1)
        )
        sbar.close()
        with torch.no_grad():
            # the last step's clean x0 prediction (as the scene prior's inpaint; for SD2 it equals z at
            # alpha_bar_0 up to sqrt(1 - alpha_bar_0) of predicted noise)
            x = denoiser.decode(res.x0).clamp(0, 1).float()
            e_in, e_out = float(energy(prob.image)), float(energy(x))
        fill = x[0].permute(1, 2, 0).numpy()
        back = _resize(fill, prob.side, prob.side)
        full = inp_n.copy()
        H, W = mask.shape
        ys = slice(max(prob.y0, 0), min(prob.y0 + prob.side, H))
        xs = slice(max(prob.x0, 0), min(prob.x0 + prob.side, W))
        full[ys, xs] = back[ys.start - prob.y0 : ys.stop - prob.y0, xs.start - prob.x0 : xs.stop - prob.x0]
        out = paste(inp_n, np.clip(full, 0, 1), mask, cfg.feather_px)
        r_before, n_sup = consistency_residual(inp_n, inp_k, cam, cam_k, points, mask, depth_k, device)
        written = to_uint8(out).astype(np.float32) / 255  # the residual of what the PNG holds
        r_after, _ = consistency_residual(written, inp_k, cam, cam_k, points, mask, depth_k, device)
        rec = {
            "view": n, "status": "guided" if cfg.guidance_scale else "unguided", "steps": n_steps,
            "energy_input": e_in, "energy_output": e_out, "energies": res.energies,
            "residual_before": r_before, "residual_after": r_after, "support_px": n_sup,
            "support_work_px": int(prob.support.sum()), "hole_work_px": int(prob.hole.sum()),
            "n_points": int(len(points)), "crop": [prob.y0, prob.x0, prob.side], "work": work,
            "seconds": time.perf_counter() - t0,
        }  # fmt: skip
        # the JSON first: a PNG present means the view is complete (resume checks the PNG)
        atomic_write(js, lambda p, r=rec: p.write_text(json.dumps(r, indent=1)))
        write_png(png, out)
        records[stem] = rec
        log.info("CLG: view %d (%s): energy %.4f -> %.4f, residual %.4f -> %.4f, %.1f s",
                 n, stem, e_in, e_out, r_before, r_after, rec["seconds"])  # fmt: skip
    bar.close()
    status = [r["status"] for r in records.values()]
    return {
        "views": records,
        "n_guided": sum(s in ("guided", "unguided", "warped") for s in status),
        "n_skipped": status.count("skipped"),
        "n_resumed": status.count("resumed"),
        "steps": n_steps if cfg.sample else 0,
        "model": getattr(denoiser, "name", type(denoiser).__name__) if cfg.sample else "none (warp only)",
        "features": getattr(features, "name", type(features).__name__) if cfg.sample else None,
        "n_points": int(len(points)),
        "reference": k,
    }


# ----------------------------------------------------------------------------------------------------
# the pipeline stage


def stage_clg(ctx: Any, scene: Any = None, masks: list[np.ndarray] | None = None) -> dict[str, Any]:
    """Stage 3_clg of `coin_cl.pipeline.coin`: reads 1_inpaint (I^_n, the scene prior's cache) and
    2_refgs (renders/, depths/, alphas/, reference_points.ply); writes images/<stem>.png per guided view.
    scene, masks: the views as the pipeline's stages see them (default `ctx.shared`'s)."""
    from dataclasses import replace

    from coin_cl.diffusion.features import make_feature_extractor
    from coin_cl.diffusion.scene_prior import cache_key
    from coin_cl.gs.refgs import composite_targets
    from coin_cl.pipeline.inpaint2d import effective_config, read_inpaints, stage_prior
    from coin_cl.scene.io import read_image

    scene = ctx.shared["scene"] if scene is None else scene
    masks = ctx.shared["masks"] if masks is None else masks
    train = list(scene.train_idx)
    k = int(ctx.shared["ref"])
    ccfg = ctx.shared["cfg"]
    cfg: CLGConfig = ccfg.clg or CLGConfig()
    cfg = replace(cfg, seed=ccfg.seed, prompt=cfg.prompt or ccfg.prompt)
    inp = read_inpaints(scene, ctx.inputs["1_inpaint"], train)
    inpaints: list[np.ndarray | None] = [None] * len(scene)
    for i in train:
        inpaints[i] = composite_targets(inp[i], scene.images[i], masks[i])
    gs = ctx.inputs["2_refgs"]
    renders: list[np.ndarray | None] = [None] * len(scene)
    depths: list[np.ndarray | None] = [None] * len(scene)
    for i in train:
        stem = _stem(scene.cameras[i], i)
        renders[i] = read_image(gs / "renders" / f"{stem}.png")
        d = np.load(gs / "depths" / f"{stem}.npy")
        a = gs / "alphas" / f"{stem}.npy"
        if a.is_file():
            d = np.where(np.load(a) > 0.5, d, np.nan)  # depth means a surface only where alpha > 0.5
        depths[i] = d
    ply = gs / "reference_points.ply"
    if ply.is_file():
        from coin_cl.scene.ply import read_points_ply

        points, _ = read_points_ply(ply)
        ctx.note(f"P_k: {len(points)} points from {ply.name}")
    else:
        points = reference_points(scene.cameras[k], depths[k], masks[k])
        ctx.note(f"P_k: {len(points)} points unprojected from the reference render's depth")
    if (ctx.inputs["1_inpaint"] / "edit" / "points.ply").is_file():
        cfg = replace(cfg, sample=False)
        ctx.note("edited reference: no sampler (no model here can draw the inserted object); each hole pixel "
                 "takes the reference warped through P_k, or R_n where P_k does not reach")  # fmt: skip
    if not cfg.sample:
        denoiser = None
    elif ccfg.sd_path:
        from coin_cl.diffusion.sd2 import SD2Denoiser

        denoiser = SD2Denoiser.from_pretrained(ccfg.sd_path)
    else:
        cam = scene.cameras[train[0]]
        icfg = effective_config(
            ccfg.inpaint2d, ctx.shared["iters"]["prior_seconds"], ccfg.seed, cam.width, cam.height
        )
        folder = ctx.inputs["1_inpaint"]
        key = cache_key([scene.images[i] for i in train], [masks[i] for i in train], icfg.prior)
        if not (folder / f"scene_prior_{key}.pt").is_file():
            folder = ctx.out  # never write into an earlier stage's folder (its manifest hashes it)
        denoiser = stage_prior(scene, masks, train, icfg, folder)
    if denoiser is not None:
        ctx.note(f"CLG model: {denoiser.name}")
        extractor, fname = make_feature_extractor(ccfg.dino_path)
        ctx.note(f"CLG features: {fname}")
    else:
        extractor = None
    res = run_clg(k, train, scene.cameras, inpaints, renders, depths, masks, points, denoiser, extractor,
                  ctx.out, cfg, device=ccfg.device)  # fmt: skip
    for stem, r in res["views"].items():
        if r["status"] == "skipped":
            ctx.note(f"view {stem} skipped: {r['reason']}")
    return res
