"""The reference view k (CoIn paper 4.2): which view leads Ref-GS and CLG, by `--ref` or by the
largest, most central mask; used by removal and insertion alike (4.2) - and its points P_k: the
reference's depth unprojected around the mask, which CLG and TE-D warp through (4.3, 4.4)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import cv2
import numpy as np

from coin_cl.scene.masks import bbox

if TYPE_CHECKING:
    from coin_cl.scene import Camera, Scene

log = logging.getLogger(__name__)


def reference_score(mask: np.ndarray) -> float:
    """Score of a view as reference: area fraction of its mask x centrality, where centrality =
    1 - |mask centroid - image centre| / half the image diagonal (1 at the centre, 0 in a
    corner). A large hole seen head-on gives the reference the most content to impose; a
    central one keeps that content in view of the neighbouring cameras. Empty mask: 0."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 0.0
    H, W = m.shape
    ys, xs = np.nonzero(m)
    # Pixel centres at +0.5, image centre at (W/2, H/2).
    dist = math.hypot(xs.mean() + 0.5 - W / 2, ys.mean() + 0.5 - H / 2)
    centrality = 1.0 - dist / (0.5 * math.hypot(W, H))
    return float(m.mean() * centrality)


def resolve_reference(ref: str | int, names: Sequence[str], candidates: Sequence[int]) -> int:
    """The view index that `--ref` names.

    Args:
        ref: an int index, a string of digits (an index), or a view name (with or without its
            extension).
        names: name of every view; candidates: indices allowed (the training views).
    Raises:
        ValueError with the allowed values when `ref` is unknown or not a training view.
    """
    cands = list(candidates)
    if isinstance(ref, bool) or not isinstance(ref, int | str | np.integer):
        raise ValueError(f"--ref must be a view name or index, got {ref!r}")
    idx: int | None = None
    if isinstance(ref, int | np.integer):
        idx = int(ref)
    else:
        s = ref.strip()
        stems = [n.rsplit(".", 1)[0] if "." in n else n for n in names]
        key = s.rsplit(".", 1)[0] if "." in s else s
        hits = [i for i, n in enumerate(names) if n == s] or [i for i, st in enumerate(stems) if st == key]
        if hits:
            idx = hits[0]
            # "12" naming view "12.png" while index 12 is another training view: say both readings.
            if s.isdigit() and s == str(int(s)) and int(s) in cands and int(s) != idx:
                raise ValueError(
                    f"--ref {ref!r} is ambiguous: the view named {names[idx]!r} (index {idx}) or the view at "
                    f"index {int(s)} ({names[int(s)]!r}); give the name with its extension, or the index "
                    "as an int from Python"
                )
        elif s.lstrip("-").isdigit():
            idx = int(s)
    shown = ", ".join(f"{i} ({names[i]})" for i in cands[:12]) + (" ..." if len(cands) > 12 else "")
    if idx is None:
        raise ValueError(f"--ref {ref!r}: no view of that name; training views: {shown}")
    if idx not in cands:
        raise ValueError(f"--ref {ref!r}: view {idx} is not a training view; training views: {shown}")
    return idx


def choose_reference(
    scene_or_masks: Scene | Sequence[np.ndarray],
    cameras: Sequence[Camera] | None = None,
    *,
    train_idx: Sequence[int] | None = None,
    ref: str | int | None = None,
) -> int:
    """The reference view k.

    With `ref` (the `--ref` option): `resolve_reference`. Otherwise the training view with the
    highest `reference_score` (largest, most central mask); ties go to the lowest index.

    Args:
        scene_or_masks: a Scene (masks, cameras, train_idx taken from it) or a sequence of
            [H, W] bool masks (one per view).
        cameras: camera-likes aligned with the masks (used for names); taken from the scene.
        train_idx: candidate views (default the scene's training views, else all views).
    Returns:
        the view index.
    """
    if hasattr(scene_or_masks, "masks"):
        masks = list(scene_or_masks.masks)
        cameras = list(scene_or_masks.cameras) if cameras is None else list(cameras)
        if train_idx is None and getattr(scene_or_masks, "train_idx", None):
            train_idx = list(scene_or_masks.train_idx)
    else:
        masks = list(scene_or_masks)
    if not masks:
        raise ValueError("choose_reference: no views")
    cands = list(range(len(masks))) if train_idx is None else [int(i) for i in train_idx]
    if not cands:
        raise ValueError("choose_reference: no candidate (training) views")
    if cameras is not None and len(cameras) != len(masks):
        raise ValueError(f"{len(cameras)} cameras but {len(masks)} masks")
    names = (
        [str(getattr(c, "name", "") or i) for i, c in enumerate(cameras)]
        if cameras
        else [str(i) for i in range(len(masks))]
    )
    if ref is not None:
        return resolve_reference(ref, names, cands)
    scores = [reference_score(masks[i]) for i in cands]
    best = cands[int(np.argmax(scores))]  # argmax returns the first maximum: lowest index wins
    if scores[cands.index(best)] == 0.0:
        log.warning("choose_reference: every candidate mask is empty; using view %d", best)
    return best


# ---------------------------------------------------------------------------------------------
# P_k: the reference's points (paper 4.3; written by the Ref-GS stage, read by CLG and TE-D)


def pk_margin_px(mask: np.ndarray) -> int:
    """Margin around the mask kept in P_k: max(4, 10 % of the bounding box's larger side) px. The
    margin carries the hole's rim, which TE-D's warps need to blend the fill into its surroundings."""
    box = bbox(np.asarray(mask, bool))
    if box is None:
        return 4
    y0, y1, x0, x1 = box
    return int(max(4, round(0.1 * max(y1 - y0, x1 - x0))))


def reference_pixels(
    depth: np.ndarray, mask: np.ndarray, margin_px: int | None = None, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The reference pixels that make P_k: inside the mask dilated by margin_px (elliptic kernel;
    default `pk_margin_px`), with finite depth > 0 and inside `valid` when given.

    Args:
        depth: [H, W] camera z; mask: [H, W] bool; valid: optional [H, W] bool (e.g. alpha > 0.5).
    Returns:
        (ys [M], xs [M]) int64, row-major order.
    """
    depth = np.asarray(depth)
    mask = np.asarray(mask, bool)
    if depth.shape != mask.shape:
        raise ValueError(f"depth {depth.shape} and mask {mask.shape} differ")
    if valid is not None and np.shape(valid) != mask.shape:
        raise ValueError(f"valid has shape {np.shape(valid)}, expected {mask.shape}")
    m = pk_margin_px(mask) if margin_px is None else int(margin_px)
    if m < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    region = cv2.dilate(mask.astype(np.uint8), ker).astype(bool)
    with np.errstate(invalid="ignore"):
        sel = region & np.isfinite(depth) & (depth > 0)
    if valid is not None:
        sel &= np.asarray(valid, bool)
    return np.nonzero(sel)


def reference_points(
    camera: Camera,
    depth: np.ndarray,
    mask: np.ndarray,
    margin_px: int | None = None,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """P_k from a depth map of the reference view (GS render, ground truth, ...): the
    `reference_pixels` unprojected at their pixel centres (+0.5) to world points.

    Args:
        camera: the reference `Camera` (K, viewmat, width, height).
        depth: [H, W] camera z; pixels with non-finite or <= 0 depth are left out.
        mask: [H, W] bool inpainting mask of the reference view.
        margin_px: dilation radius in pixels, >= 0 (default `pk_margin_px`).
        valid: optional [H, W] bool, e.g. rendered alpha > 0.5 (pixels where the depth means a surface).
    Returns:
        [M, 3] float32 world points, row-major pixel order (M may be 0).
    """
    depth = np.asarray(depth, dtype=np.float64)
    H, W = int(camera.height), int(camera.width)
    if depth.shape != (H, W) or np.shape(mask) != (H, W):
        raise ValueError(f"depth {depth.shape} and mask {np.shape(mask)} must be the camera's ({H}, {W})")
    ys, xs = reference_pixels(depth, mask, margin_px, valid)
    uv = np.stack([xs + 0.5, ys + 0.5], 1).astype(np.float64)
    return camera.unproject(uv, depth[ys, xs]).astype(np.float32)
