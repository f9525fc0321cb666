"""Point pruning by mask votes (CoIn paper 4.2, Ref-GS): SfM points that project into the masks
(in at least `min_fraction` of the views that see them) are removed before the anchors are built,
so that the residual object in the COLMAP points cannot come back. The vote itself is
`coin_cl.scene.geometry.mask_vote_counts`, shared with the scene checks and mask refinement."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from coin_cl.engine import constants as cst
from coin_cl.scene.geometry import mask_vote_counts


class PruneResult(NamedTuple):
    """points [M, 3] kept, n_removed, keep [P] bool over the input points (to slice colours)."""

    points: np.ndarray
    n_removed: int
    keep: np.ndarray


def in_masks(
    points: Any, cameras: Sequence[Any], masks: Sequence[Any], min_fraction: float, min_views: int = 1
) -> np.ndarray:
    """[P] bool: the points seen by at least `min_views` of the views (beyond the renderer's near
    plane, inside the image: what it could draw) whose pixel is inside the view's mask in at least
    `min_fraction` of the views that see them (the vote of `prune_points_in_masks`; also the visual
    hull of insertion and the Gaussians removed by the mask refinement).

    Args:
        points: [P, 3] world positions (numpy or torch); cameras, masks: aligned views, [H, W] bool.
    """
    seen, inside = mask_vote_counts(points, cameras, masks, near=cst.NEAR_PLANE)
    return (seen >= max(1, min_views)) & (inside >= min_fraction * seen)


def prune_points_in_masks(
    points: np.ndarray,
    cameras: Sequence[Any],
    masks: Sequence[Any],
    min_fraction: float = 0.5,
    min_views: int = 1,
) -> PruneResult:
    """Remove SfM points that fall inside the masks.

    A point is removed when it is seen (in front of the camera, inside the image) by at least
    `min_views` of the given views and its pixel is inside the mask in at least `min_fraction` of
    those views. Points seen by fewer views are kept: nothing says they are on the object.
    The default 0.5 (a majority) removes points on the object, which are inside the mask from
    every view, but keeps background points that the object hides only from some views.

    Args:
        points: [P, 3] world positions.
        cameras, masks: the views to vote with (normally the training views) and their [H, W] bool
            masks, aligned.
    Returns:
        PruneResult(points [M, 3] (same dtype as the input), n_removed, keep [P] bool).
    """
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be [P, 3], got {pts.shape}")
    remove = in_masks(pts, cameras, masks, min_fraction, min_views)
    keep = ~remove
    return PruneResult(pts[keep], int(remove.sum()), keep)
