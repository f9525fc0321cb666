"""Multi-view geometry helpers on a `Scene`: which sparse points lie on the masked object, and how
well masks agree across views (used by checks and by the pipeline's 3D-first option)."""

from __future__ import annotations

import numpy as np

from .types import Scene


def mask_votes(scene: Scene, points: np.ndarray, views: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """For points (N, 3): in how many of `views` each lands inside the image in front of the
    camera (seen (N,)), and in how many of those inside the view's mask (inside (N,))."""
    seen = np.zeros(len(points), np.int32)
    inside = np.zeros(len(points), np.int32)
    for i in views:
        cam, m = scene.cameras[i], scene.masks[i]
        uv, z = cam.project(points)
        ok = cam.in_image(uv) & (z > 0)
        px = np.floor(uv[ok]).astype(np.int64)
        hit = np.zeros(len(points), bool)
        hit[np.flatnonzero(ok)] = m[px[:, 1], px[:, 0]]
        seen += ok
        inside += hit
    return seen, inside


def object_points(
    scene: Scene, views: list[int] | None = None, min_views: int = 3, min_frac: float = 0.9
) -> np.ndarray:
    """Indices of sparse points on the masked object: seen in >= min_views of `views` (default the
    training views) and inside the mask in >= min_frac of those. (M,) int64."""
    views = scene.train_idx if views is None else views
    seen, inside = mask_votes(scene, scene.points, views)
    ok = (seen >= min_views) & (inside >= min_frac * np.maximum(seen, 1))
    return np.flatnonzero(ok)
