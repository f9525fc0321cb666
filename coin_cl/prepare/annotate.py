"""The object in one view, from what a user can draw in a minute: a box, a scribble or a mask
(the one annotation `propagate_masks` spreads to every view, the input CoIn's section 4 assumes).

- box (x0, y0, x1, y1) pixels: GrabCut initialised with the rectangle;
- scribble: an image whose non-zero pixels are strokes ON the object; GrabCut with the strokes as
  sure object and a box around them (grown by `SCRIBBLE_REACH`) as where the object may be;
- mask: an image whose non-zero pixels are the object, taken as is.

Annotation images may be at the photo's size or the prepared (working) size, same aspect ratio;
they are resized (nearest) to the view. A `segment` hook (`propagate.Segmenter`) replaces GrabCut.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..scene.masks import read_mask
from ..scene.types import resize_mask
from .propagate import Segmenter, grabcut_segment, keep_largest_components

log = logging.getLogger(__name__)

# A scribble's box is grown by this fraction of its size on each side: strokes rarely reach the rim.
SCRIBBLE_REACH = 0.35
MIN_BOX = 4  # pixels: a smaller box is a slip of the mouse


def resolve_view(view: str | int, names: Sequence[str]) -> int:
    """A view given by index or (file) name, with or without extension -> index; clear error."""
    s = str(view).strip()
    stems = [Path(n).stem for n in names]
    for i, n in enumerate(names):
        if s == n or s == stems[i] or Path(s).stem == stems[i]:
            return i
    if s.lstrip("-").isdigit() and 0 <= int(s) < len(names):
        return int(s)
    shown = ", ".join(names[:5]) + (" ..." if len(names) > 5 else "")
    raise ValueError(
        f"view {view!r} is not a prepared view; give an index 0..{len(names) - 1} or a name ({shown})"
    )


def check_box(box: Sequence[float], width: int, height: int, view: str) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) in pixels -> ints clipped to the image; errors for a box outside it."""
    if len(box) != 4:
        raise ValueError(f"--box needs 4 numbers x0 y0 x1 y1, got {list(box)}")
    x0, y0, x1, y1 = (float(v) for v in box)
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise ValueError(
            f"box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) lies outside view {view} ({width}x{height} px); "
            "give x0 y0 x1 y1 in that image's pixels"
        )
    c = (max(0, round(x0)), max(0, round(y0)), min(width, round(x1)), min(height, round(y1)))
    if c != (round(x0), round(y0), round(x1), round(y1)):
        log.warning("box clipped to view %s: %s", view, c)
    if c[2] - c[0] < MIN_BOX or c[3] - c[1] < MIN_BOX:
        raise ValueError(f"box {c} in view {view} is smaller than {MIN_BOX} px; draw it around the object")
    if c[2] - c[0] >= width and c[3] - c[1] >= height:
        raise ValueError(f"box {c} covers all of view {view}; draw it around the object only")
    return c


def read_annotation(path: str | Path, width: int, height: int) -> np.ndarray:
    """A scribble or mask image at the view's size or the same aspect ratio -> (height, width) bool."""
    m = read_mask(path)
    h, w = m.shape
    if (w, h) != (width, height):
        if abs(w / h - width / height) > 0.01 * width / height:
            raise ValueError(
                f"annotation {path} is {w}x{h} but the view is {width}x{height}; draw it on the photo "
                "or on the prepared image (same aspect ratio)"
            )
        m = resize_mask(m, width, height)
    if not m.any():
        raise ValueError(f"annotation {path} is empty; non-zero pixels must mark the object")
    if m.all():
        raise ValueError(
            f"annotation {path} covers the whole image; non-zero pixels must mark the object only"
        )
    return m


def box_mask(image: np.ndarray, box: tuple[int, int, int, int], segment: Segmenter | None = None,
             iters: int = 5) -> np.ndarray:  # fmt: skip
    """The object inside `box` (x0, y0, x1, y1) of `image` (H, W, 3): (H, W) bool."""
    H, W = image.shape[:2]
    x0, y0, x1, y1 = box
    rect = np.zeros((H, W), bool)
    rect[y0:y1, x0:x1] = True
    if segment is not None:
        return np.asarray(segment(image, rect, np.zeros((0, 2)), np.zeros((0, 2))), bool)
    gc = np.zeros((H, W), np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    img8 = np.ascontiguousarray((np.clip(image, 0, 1) * 255).astype(np.uint8))
    cv2.grabCut(img8, gc, (x0, y0, x1 - x0, y1 - y0), bgd, fgd, iters, cv2.GC_INIT_WITH_RECT)
    out = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    if out.sum() < 0.05 * rect.sum():
        log.warning("GrabCut found almost nothing in the box; using the box itself as the mask")
        return rect
    return keep_largest_components(out, np.zeros((0, 2)))


def scribble_mask(image: np.ndarray, strokes: np.ndarray, segment: Segmenter | None = None,
                  iters: int = 5) -> np.ndarray:  # fmt: skip
    """The object under `strokes` (H, W) bool drawn on it: (H, W) bool."""
    H, W = strokes.shape
    ys, xs = np.nonzero(strokes)
    gx = SCRIBBLE_REACH * (xs.max() - xs.min() + 1)
    gy = SCRIBBLE_REACH * (ys.max() - ys.min() + 1)
    g = max(gx, gy, 4)
    x0, x1 = int(max(0, xs.min() - g)), int(min(W, xs.max() + g + 1))
    y0, y1 = int(max(0, ys.min() - g)), int(min(H, ys.max() + g + 1))
    prior = np.zeros((H, W), bool)
    prior[y0:y1, x0:x1] = True
    seeds = np.stack([xs, ys], axis=1).astype(np.float64)
    if segment is not None:
        return np.asarray(segment(image, prior, seeds, np.zeros((0, 2))), bool) | strokes
    margin = max(3, int(0.02 * np.hypot(W, H)))
    # grabcut_segment marks the prior probable-object and seeds sure-object; strokes are the seeds.
    return grabcut_segment(image, prior, seeds, None, margin, iters) | strokes
