"""Observed background from the captures themselves (the 3D-first split of the paper's
supplement C.2): the colour of a mask pixel that another view sees is that view's captured pixel,
carried through the object-free geometry, not a render of a GS fitted to the captures.

Off by default (`RefineConfig.warp_tol` = 0), measured on the demo room (18 training views, exact
visibility, CoIn at the demo's steps; docs/RESULTS.md "Observed background warped from the
captures"): where the split already marks a pixel observed, the render R^rmv_n is as good as the
warp (texture 0.92 / 0.91 of the truth's, 27.2 / 27.0 dB), so colours alone gained nothing; as a
visibility test it halves the exactly observed pixels marked unseen (0.24 -> 0.10) but takes 29 %
of the unseen core for observed (recall 0.96 -> 0.71: the object-free depth shows a surface
behind one nobody saw, and a view does capture that one), and end to end it moved m-PSNR +0.25
dB, HF -0.01 and bbox GMSD +0.018 (worse).

For view n's pixel p with the object-free depth d(p) (G^rmv's expected depth): X = unproject(p,
d(p)) is projected into every other training view m. m observes X when X lands in m's frame,
outside m's mask (grown by 1 px, so bilinear sampling never reads the object's colour), and m's
captured surface (the depth of the fit with the object, 0 where none) lies at X's camera z within
`tol` (relative): nothing stands in front of X in m. Of the views that observe X the one whose ray
makes the smallest angle with n's ray gives the colour (bilinear; the least parallax and the
least view-dependent change). A pixel with no such view keeps its old source (unseen, or the
render R^rmv_n).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from coin_cl.scene import Camera


def warp_observed(
    cams: dict[int, Camera],
    images: dict[int, np.ndarray],
    masks: dict[int, np.ndarray],
    depth_n: np.ndarray,
    captured_depth: dict[int, np.ndarray],
    cam_n: Camera,
    pixels: np.ndarray,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours of view n's `pixels` taken from the other views' captures.

    Args:
        cams: {m: scene camera} of the source views (view n itself excluded by the caller).
        images: {m: (H, W, 3) float [0, 1] captured image}.
        masks: {m: (H, W) bool object mask}.
        depth_n: (H, W) object-free camera z of view n (NaN or <= 0: no surface).
        captured_depth: {m: (H, W) camera z of the surface view m captured, object included; 0 where none}.
        cam_n: view n's scene camera.
        pixels: (H, W) bool, the pixels to fill.
        tol: relative depth agreement that makes X visible in m.
    Returns:
        (colours (H, W, 3) float32, zero outside `found`; found (H, W) bool, a subset of `pixels`;
        source (H, W) int, the view index used, -1 where none).
    """
    if not tol > 0 or not np.isfinite(tol):
        raise ValueError(f"warp_observed: tol must be a positive finite number, got {tol}")
    H, W = pixels.shape
    colours = np.zeros((H, W, 3), np.float32)
    source = np.full((H, W), -1, np.int64)
    ys, xs = np.nonzero(pixels)
    if not len(ys) or not cams:
        return colours, np.zeros((H, W), bool), source
    d = np.asarray(depth_n, np.float64)[ys, xs]
    ok = np.isfinite(d) & (d > 0)
    ys, xs, d = ys[ok], xs[ok], d[ok]
    X = cam_n.unproject(np.stack([xs + 0.5, ys + 0.5], 1), d)
    ray_n = X - cam_n.camtoworld[:3, 3]
    ray_n /= np.linalg.norm(ray_n, axis=1, keepdims=True)
    best_cos = np.full(len(X), -np.inf)
    best_col = np.zeros((len(X), 3), np.float32)
    best_src = np.full(len(X), -1, np.int64)
    ker = np.ones((3, 3), np.uint8)
    for m, cam in cams.items():
        uv, z = cam.project(X)
        px, inside = cam.pixels(X)
        grown = cv2.dilate(np.asarray(masks[m], np.uint8), ker) > 0
        free = inside & ~grown[px[:, 1], px[:, 0]]
        dm = np.asarray(captured_depth[m], np.float64)[px[:, 1], px[:, 0]]
        with np.errstate(invalid="ignore"):
            vis = free & (dm > 0) & (np.abs(z - dm) <= tol * dm)
        if not vis.any():
            continue
        ray_m = X - cam.camtoworld[:3, 3]
        cos = (ray_n * ray_m).sum(1) / np.linalg.norm(ray_m, axis=1)
        take = vis & (cos > best_cos)
        if not take.any():
            continue
        # Pixel centres at +0.5 (the scene's convention), cv2.remap samples at integer centres.
        mx = (uv[take, 0] - 0.5).astype(np.float32).reshape(-1, 1)
        my = (uv[take, 1] - 0.5).astype(np.float32).reshape(-1, 1)
        img = np.ascontiguousarray(images[m], np.float32)
        col = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
        best_cos[take], best_col[take], best_src[take] = cos[take], col, m
    hit = best_src >= 0
    found = np.zeros((H, W), bool)
    found[ys[hit], xs[hit]] = True
    colours[ys[hit], xs[hit]] = best_col[hit]
    source[ys[hit], xs[hit]] = best_src[hit]
    return colours, found, source
