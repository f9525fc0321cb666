"""Multi-view geometry helpers on posed views: which points lie on the masked object, and how well
masks agree across views (scene checks, the Ref-GS point pruning of paper 4.2, the pipeline's
3D-first mask refinement and insertion's visual hull)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .masks import mask_of_shape
from .types import Camera, Scene


def mask_vote_counts(
    points: Any, cameras: Sequence[Any], masks: Sequence[Any], near: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The one mask vote of the package.

    Args:
        points: [P, 3] world positions (numpy or torch).
        cameras: camera-likes (K, viewmat, width, height; see `Camera.from_any`); masks: their
            [H, W] bool masks (numpy or torch), aligned.
        near: a point counts as seen only at camera z > near (see `Camera.project`).
    Returns:
        (seen [P] int64: in how many views each point is in front of the camera and inside the
        image, inside [P] int64: in how many of those its pixel is inside that view's mask).
    """
    if len(cameras) != len(masks):
        raise ValueError(f"{len(cameras)} cameras but {len(masks)} masks")
    pts = np.asarray(points.detach().cpu() if hasattr(points, "detach") else points, np.float64)
    pts = pts.reshape(-1, 3)
    seen = np.zeros(len(pts), np.int64)
    inside = np.zeros(len(pts), np.int64)
    for i, (cam, mask) in enumerate(zip(cameras, masks)):
        cam = cam if isinstance(cam, Camera) else Camera.from_any(cam)
        m = mask_of_shape(mask, cam.height, cam.width, f"view {i}")
        px, ok = cam.pixels(pts, near)
        seen += ok
        inside += ok & m[px[:, 1], px[:, 0]]
    return seen, inside


def object_points(
    scene: Scene, views: list[int] | None = None, min_views: int = 3, min_frac: float = 0.9
) -> np.ndarray:
    """Indices of sparse points on the masked object: seen in >= min_views of `views` (default the
    training views) and inside the mask in >= min_frac of those. (M,) int64."""
    views = scene.train_idx if views is None else views
    seen, inside = mask_vote_counts(
        scene.points, [scene.cameras[i] for i in views], [scene.masks[i] for i in views]
    )
    ok = (seen >= min_views) & (inside >= min_frac * np.maximum(seen, 1))
    return np.flatnonzero(ok)
