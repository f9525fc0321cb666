"""The CLG energy of one view (CoIn paper 4.3, eq. "E(X) = m L3D + (1 - m) ||X - R_n||_1"):
`setup_view` builds a `ViewProblem` (crops, cameras, the reference's warped features, the support),
`make_energy` the differentiable E(X) that FreeDoM guides the sampler with (`coin_cl.pipeline.clg`).

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
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from coin_cl.crop import crop_image, crop_intrinsics, resize_to
from coin_cl.diffusion.inpaint2d import crop_box
from coin_cl.diffusion.sampling import Denoiser
from coin_cl.engine import DeviceLike, support_mask, warp_features
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.reprojection import depth_tensor
from coin_cl.scene.conventions import interpolate_pose
from coin_cl.scene.types import Camera

MAX_WARP_CHANNELS = 128  # the warp op's channel limit (engine constants.MAX_CHANNELS); DINO is chunked
MIN_FEATURE_SIDE = 32  # feature images must exceed the analytic extractor's reflect padding (14 px)


def warp_chunked(
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
    device: DeviceLike,
) -> tuple[torch.Tensor, torch.Tensor]:
    """warp_features over channel chunks of at most MAX_WARP_CHANNELS (DINO has 384); returns
    (features [h, w, C], weight [h, w])."""
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


def feature_image(extractor: Callable, img: torch.Tensor) -> torch.Tensor:
    """[1, 3, h, w] image -> [h, w, C + 3]: the extractor's channels, then RGB."""
    f = extractor(img)
    if f.dim() != 4 or f.shape[0] != 1 or f.shape[-2:] != img.shape[-2:]:
        raise ValueError(f"feature extractor returned {tuple(f.shape)} for an image {tuple(img.shape)}")
    return torch.cat([f.to(img.dtype), img], 1)[0].permute(1, 2, 0).contiguous()


@dataclass
class ViewProblem:
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


def _projected(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(uv [M, 2], ok [M]): `Camera.project` and where it is finite, in front of the camera."""
    uv, z = cam.project(points)
    return uv, np.isfinite(uv).all(1) & np.isfinite(z)


def work_size(denoiser: Denoiser) -> int:
    return int(getattr(denoiser, "work_size", 512))


def setup_view(
    cam_k: Camera,
    cam_n: Camera,
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
    device: DeviceLike,
) -> ViewProblem:
    H, W = mask_n.shape
    y0, x0, side = crop_box(mask_n, work, cfg.context)
    s = work / side
    img = resize_to(crop_image(inpaint_n, y0, x0, side, side), work, work)
    ren = resize_to(crop_image(render_n, y0, x0, side, side), work, work)
    # any coverage of a low-res pixel makes it a hole, as stage 1 (thin mask parts survive downscaling)
    cov = cv2.resize(crop_image(mask_n.astype(np.float32), y0, x0, side, side), (work, work),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    hole = cov > 0
    if hole.all():
        raise ValueError("the crop around the mask is entirely masked: nothing to condition on")
    K_n = crop_intrinsics(cam_n.K, x0, y0, s, s)
    d_n = (
        None
        if depth_n is None
        else resize_to(crop_image(depth_n.astype(np.float32), y0, x0, side, side), work, work, True)
    )

    # the reference's crop: P_k's bounding box in view k (at least MIN_FEATURE_SIDE at scale s)
    uv_k, ok_k = _projected(Camera.from_any(cam_k), points)
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
    K_k = crop_intrinsics(cam_k.K, kx0, ky0, rw / bw, rh / bh)
    ref_img = resize_to(crop_image(inpaint_k, ky0, kx0, bh, bw), rw, rh)
    d_k = (
        None
        if depth_k is None
        else resize_to(crop_image(depth_k.astype(np.float32), ky0, kx0, bh, bw), rw, rh, True)
    )

    # the intermediate camera phi, cropped to P_k's projections
    V_phi = np.asarray(interpolate_pose(cam_k.viewmat, cam_n.viewmat, cfg.alpha), dtype=np.float64)
    K_full = (1 - cfg.alpha) * np.asarray(cam_k.K) + cfg.alpha * np.asarray(cam_n.K)
    uv_p, ok_p = _projected(Camera(K_full, V_phi, W, H, "phi"), points)
    if not ok_p.any():
        raise ValueError("no point of P_k lies in front of the intermediate camera phi")
    plo, phi_hi = np.floor(uv_p[ok_p].min(0)) - 2, np.ceil(uv_p[ok_p].max(0)) + 2
    # phi is virtual (no border), but a huge box means broken geometry: cap it
    cap = 4 * max(H, W)
    plo, phi_hi = np.maximum(plo, -cap), np.minimum(phi_hi, cap)
    K_phi = crop_intrinsics(K_full, plo[0], plo[1], s, s)
    phi_w = max(1, math.ceil((phi_hi[0] - plo[0]) * s))
    phi_h = max(1, math.ceil((phi_hi[1] - plo[1]) * s))

    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    with torch.no_grad():
        fk = feature_image(
            extractor, torch.from_numpy(np.ascontiguousarray(ref_img.transpose(2, 0, 1)))[None]
        )
        ref_w, ref_wt = warp_chunked(
            pts, K_k, cam_k.viewmat, fk, K_phi, V_phi, phi_w, phi_h, depth_tensor(d_k), cfg, device
        )
        ones = torch.ones(rh, rw, 1)
        _, cov_n = warp_chunked(
            pts, K_k, cam_k.viewmat, ones, K_n, cam_n.viewmat, work, work, depth_tensor(d_k), cfg, device
        )
    hole_t = torch.from_numpy(hole)
    return ViewProblem(
        work=work, y0=y0, x0=x0, side=side,
        image=torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].float(),
        render=torch.from_numpy(np.ascontiguousarray(ren.transpose(2, 0, 1)))[None].float(),
        hole=hole_t[None, None].float(), support=support_mask(cov_n, hole_t), points=pts,
        K_n=K_n, V_n=np.asarray(cam_n.viewmat, np.float64), depth_n=depth_tensor(d_n),
        K_phi=K_phi, V_phi=V_phi, phi_w=phi_w, phi_h=phi_h, ref_warped=ref_w, ref_weight=ref_wt,
        n_hr=fk.shape[-1] - 3,
    )  # fmt: skip


def make_energy(p: ViewProblem, extractor: Callable, cfg: CLGConfig, device: DeviceLike) -> Callable:
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
            fn = feature_image(extractor, xc)
            wn, wt = warp_chunked(
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
