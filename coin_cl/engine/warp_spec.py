"""The warp op's contract, shared by the kernels' wrapper (`ops/warp.py`) and its float64 twin
(`reference_warp.py`): point status codes, footprints and the input checks."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from coin_cl.engine import constants as cst

FOOTPRINTS = {"nearest": 0, "bilinear": 1}
# Per-point status codes written by kernels/warp.cl (a point gets its first failure).
STATUS = ("ok", "nonfinite", "behind_src", "outside_src", "occluded_src", "behind_dst", "outside_dst")


def _as_tensor(x, name: str, shape: tuple[int, ...]) -> Tensor:
    t = torch.as_tensor(x).detach().to(torch.float64)
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} holds NaN or Inf: cameras must be finite")
    return t


def camera_vector(K, viewmat, name: str = "camera") -> Tensor:
    """[16] float32 [R (row-major), t, fx, fy, cx, cy], the layout kernels/warp.cl reads."""
    k = _as_tensor(K, f"{name} K", (3, 3))
    v = _as_tensor(viewmat, f"{name} viewmat", (4, 4))
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f"{name} K must have positive focal lengths, got fx={k[0, 0]}, fy={k[1, 1]}")
    return torch.cat(
        [v[:3, :3].reshape(-1), v[:3, 3], torch.stack([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])]
    ).float()


def check_inputs(
    points: Tensor,
    src_features: Tensor,
    dst_width: int,
    dst_height: int,
    src_depth: Tensor | None,
    depth_tol: float,
    src_depth_tol: float,
    footprint: str,
) -> None:
    """Shape and range checks shared by the op and its twin (clear errors, never a kernel crash)."""
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [M, 3], got {tuple(points.shape)}")
    if src_features.dim() != 3:
        raise ValueError(f"src_features must have shape [H, W, C], got {tuple(src_features.shape)}")
    h, w, c = src_features.shape
    if h < 1 or w < 1:
        raise ValueError(f"src_features has an empty image ({h}x{w})")
    if not 1 <= c <= cst.MAX_CHANNELS:
        raise ValueError(f"src_features has {c} channels; 1 to {cst.MAX_CHANNELS} are supported")
    if src_depth is not None and tuple(src_depth.shape) != (h, w):
        raise ValueError(
            f"src_depth must have shape {(h, w)} (the feature image's), got {tuple(src_depth.shape)}"
        )
    if int(dst_width) < 1 or int(dst_height) < 1:
        raise ValueError(f"target size must be at least 1x1, got {dst_width}x{dst_height}")
    for name, tol in (("depth_tol", depth_tol), ("src_depth_tol", src_depth_tol)):
        if not (math.isfinite(tol) and tol >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {tol}")
    if footprint not in FOOTPRINTS:
        raise ValueError(f"footprint must be one of {sorted(FOOTPRINTS)}, got {footprint!r}")
