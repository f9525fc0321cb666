"""Crops and resizes of images, and the crop cameras that go with them (CoIn paper 4.1's
mask-centred crops, 4.3's CLG at the sampler's working size). A crop and a resize of an image are a
change of intrinsics, K' = diag(sx, sy, 1) (K - [0 0 x0; 0 0 y0; 0 0 0]). Pixel centres are at
+0.5, so this matches cv2's area/cubic resizes exactly.

Numpy and OpenCV only: both the 2D branch (`diffusion.inpaint2d`, which never imports the engine
or the pipeline) and the pipeline (CLG) import it."""

from __future__ import annotations

import cv2
import numpy as np


def crop_intrinsics(K: np.ndarray, x0: float, y0: float, sx: float, sy: float) -> np.ndarray:
    """Intrinsics [3, 3] of the image cropped at (x0, y0) then resized by (sx, sy)."""
    Kc = np.array(K, dtype=np.float64, copy=True)
    Kc[0, 2] -= x0
    Kc[1, 2] -= y0
    return np.diag([sx, sy, 1.0]) @ Kc


def crop_image(a: np.ndarray, y0: int, x0: int, side_y: int, side_x: int) -> np.ndarray:
    """[H, W, ...] -> [side_y, side_x, ...]: rows [y0, y0 + side_y), columns [x0, x0 + side_x),
    reflect-padding what lies outside the image (as stage 1 does, so the sampler sees the same
    context)."""
    H, W = a.shape[:2]
    pt, pl = max(-y0, 0), max(-x0, 0)
    pb, pr = max(y0 + side_y - H, 0), max(x0 + side_x - W, 0)
    if pt or pl or pb or pr:
        a = np.pad(a, [(pt, pb), (pl, pr)] + [(0, 0)] * (a.ndim - 2), mode="symmetric")
    return a[y0 + pt : y0 + pt + side_y, x0 + pl : x0 + pl + side_x]


def resize_to(a: np.ndarray, w: int, h: int, nearest: bool = False) -> np.ndarray:
    """[H, W, ...] -> [h, w, ...]: area average when shrinking, bicubic when enlarging, nearest
    neighbour for depth maps (`nearest`: no depth is invented between surfaces)."""
    if a.shape[1] == w and a.shape[0] == h:
        return a
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if a.shape[1] > w else cv2.INTER_CUBIC
    return cv2.resize(a, (w, h), interpolation=interp)
