"""Reprojection through P_k (CoIn paper 4.3): the reference view warped into another view through
the reference's points, and how far a view is from it. CLG records the residual before and after
each view, CLG without a sampler fills with the warp, insertion propagates the edited reference
with it, and benchmarks and tests score the residual to the reference with the depth variant."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from coin_cl.engine import DeviceLike, warp_features

if TYPE_CHECKING:
    from coin_cl.scene import Camera


def depth_tensor(d: np.ndarray | None) -> torch.Tensor | None:
    """[H, W] depth for the warp's occlusion test as a float32 tensor; non-finite = empty."""
    if d is None:
        return None
    d = np.where(np.isfinite(d), d, 0.0).astype(np.float32)  # non-finite = empty: nothing occludes
    return torch.from_numpy(np.ascontiguousarray(d))


def reference_in_view(
    image_k: np.ndarray,
    cam_n: Camera,
    cam_k: Camera,
    points: np.ndarray,
    depth_k: np.ndarray | None = None,
    device: DeviceLike = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The reference image_k (Hk, Wk, 3) warped into view n at full resolution through P_k
    `points` [M, 3] (`warp_features`: k -> n, occlusion-tested against depth_k): (H, W, 3) colours
    and (H, W) weights (0 where no point lands)."""
    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    with torch.no_grad():
        wk, wt, _ = warp_features(
            pts, cam_k.K, cam_k.viewmat, torch.from_numpy(np.ascontiguousarray(image_k, dtype=np.float32)),
            cam_n.K, cam_n.viewmat, cam_n.width, cam_n.height, src_depth=depth_tensor(depth_k), device=device,
        )  # fmt: skip
    return wk.numpy(), wt.numpy()


def consistency_residual(
    image_n: np.ndarray,
    image_k: np.ndarray,
    cam_n: Camera,
    cam_k: Camera,
    points: np.ndarray,
    mask_n: np.ndarray,
    depth_k: np.ndarray | None = None,
    device: DeviceLike = None,
) -> tuple[float, int]:
    """Masked reprojection error of view n to the reference through P_k: the reference image warped
    into view n at full resolution (`warp_features(P_k: k -> n)`), compared inside the support
    mask_n & (weight > 0) as the mean over pixels of the mean absolute RGB difference ([0, 1] units).

    Returns (residual, number of supported pixels); (nan, 0) without support.
    """
    warped, weight = reference_in_view(image_k, cam_n, cam_k, points, depth_k, device)
    return masked_residual(image_n, warped, weight, mask_n)


def masked_residual(
    image_n: np.ndarray, warped: np.ndarray, weight: np.ndarray, mask_n: np.ndarray
) -> tuple[float, int]:
    """`consistency_residual` given the warp already made (`reference_in_view`'s (H, W, 3) colours
    and (H, W) weights), so several images of one view are compared against one warp."""
    sup = np.asarray(mask_n, bool) & (weight > 0)
    n = int(sup.sum())
    if n == 0:
        return float("nan"), 0
    d = np.abs(np.asarray(image_n, np.float32) - warped[..., :3]).mean(-1)
    return float(d[sup].mean()), n


def warp_fill(
    image_n: np.ndarray, render_n: np.ndarray, mask_n: np.ndarray, warped: np.ndarray, weight: np.ndarray
) -> tuple[np.ndarray, int]:
    """CLG without a sampler (`CLGConfig.sample` False) for one view: inside mask_n (H, W) bool, the
    reference warped into view n (`reference_in_view`'s (H, W, 3) colours and (H, W) weights) where
    supported (weight > 0), render_n elsewhere; outside the mask image_n.
    Returns ((H, W, 3) float32, supported pixels)."""
    m = np.asarray(mask_n, bool)
    sup = m & (weight > 0)
    fill = np.where(sup[..., None], warped, render_n)
    return np.where(m[..., None], fill, image_n).astype(np.float32), int(sup.sum())


def residual_to_reference(
    cameras: Sequence[Camera],
    depths: Sequence[np.ndarray | None],
    images: Sequence[np.ndarray | None],
    regions: Sequence[np.ndarray | None],
    k: int,
    image_k: np.ndarray,
    mask_k: np.ndarray,
) -> float:
    """Mean |I_n(p) - image_k(reproject_k(p))| (mean over RGB, then over pixels) over the pixels p
    of `regions[n]` (every view n != k with a region) whose point, unprojected at `depths[n]` (camera
    z, pixel centres), lands in front of the reference camera, inside its image and inside `mask_k`:
    how far the views are from the reference's content in the hole. No occlusion test: pass the
    depths of the surfaces to compare (a render's, or the object-absent truth).

    Args:
        cameras: per view, a `Camera`; depths: per view [H, W]; images: per view [H, W, 3] in [0, 1];
        regions: per view [H, W] bool pixels to score (None: view left out).
        k: the reference view; image_k: [Hk, Wk, 3] its target; mask_k: [Hk, Wk] bool its mask.
    Returns:
        the mean, NaN when no pixel lands in the reference's mask.
    """
    ck = cameras[k]
    mk = np.asarray(mask_k, bool)
    errs = []
    for i, region in enumerate(regions):
        if i == k or region is None:
            continue
        ys, xs = np.nonzero(np.asarray(region, bool))
        if len(ys) == 0:
            continue
        depth = np.asarray(depths[i])
        pts = cameras[i].unproject(np.stack([xs + 0.5, ys + 0.5], 1), depth[ys, xs])
        px, ok = ck.pixels(pts)
        hit = ok & mk[px[:, 1], px[:, 0]]
        if not hit.any():
            continue
        img = np.asarray(images[i], np.float32)
        errs.append(np.abs(img[ys[hit], xs[hit]] - image_k[px[hit, 1], px[hit, 0]]).mean(1))
    return float(np.concatenate(errs).mean()) if errs else float("nan")
