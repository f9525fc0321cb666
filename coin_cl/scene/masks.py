"""Object masks: reading, checking, and the derived kinds the paper uses (bbox, scribble, dilated).

Every mask is (H, W) bool, True = object / region to inpaint.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

MASK_KINDS = ("seg", "bbox", "scribble")


def mask_from_array(a: np.ndarray) -> np.ndarray:
    """A mask image (grey or RGB[A], 8 or 16 bit) -> (H, W) bool.

    Rule: masks of 0/1 values (SPIn-NeRF's labels) are True where non-zero; any other mask is
    thresholded at half range (>= 128 of 255, >= 32768 of 65535). Lossy (JPEG) masks hold values
    near 0 and near 255 (ringing at the edges, noise in flat areas), which `> 0` would turn into
    speckles all over the image; half range reads them as the mask that was saved.
    Colour masks use their largest colour channel; alpha is ignored.
    """
    if a.ndim == 3:
        a = a[..., :3].max(axis=2) if a.shape[2] >= 3 else a[..., 0]
    if a.dtype == bool:
        return a
    top = 65535 if a.dtype == np.uint16 else 255 if a.dtype.kind in "ui" else 1.0
    if a.max() <= 1:
        return a > 0
    return a >= (top + 1) / 2 if a.dtype.kind in "ui" else a >= 0.5


def read_mask(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask image -> (H, W) bool (the threshold rule of `mask_from_array`: 0/1 masks
    non-zero, others at half range, so JPEG masks read right).

    shape: the (H, W) of the image it belongs to. A mask taller than the image by a few rows with
    the same width (SPIn-NeRF's 1008x576 test labels for 1008x567 images) is cropped to the top
    rows with a log line; any other mismatch raises ValueError naming the file.
    """
    from .io import imread_checked

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mask file {path} not found; add it or remove the view")
    m = mask_from_array(imread_checked(path, "mask"))
    if shape is not None and m.shape != tuple(shape):
        h, w = shape
        if m.shape[1] == w and h < m.shape[0] <= h + 16:
            log.debug("%s: mask %s taller than image %s, keeping rows 0:%d", path, m.shape, shape, h)
            m = m[:h]
        else:
            raise ValueError(
                f"mask {path} has size {m.shape[1]}x{m.shape[0]} but its image is {w}x{h}; "
                "resize the mask to the image size (nearest neighbour) or use the matching images_N"
            )
    return m


def check_mask(mask: np.ndarray, source: str = "mask") -> np.ndarray:
    """Validate a mask; returns it as bool. Empty: warning, kept. Whole image: ValueError."""
    m = np.asarray(mask).astype(bool)
    if m.ndim != 2:
        raise ValueError(f"{source}: a mask must be 2-D (H, W), got shape {m.shape}")
    if not m.any():
        log.warning("%s: mask is empty; the view is left as is (nothing to inpaint)", source)
    elif m.all():
        raise ValueError(
            f"{source}: mask covers the whole image, so nothing is left to inpaint from; "
            "check that the mask is not inverted (True/non-zero must mark the object)"
        )
    return m


def mask_of_shape(mask: Any, H: int, W: int, what: str) -> np.ndarray:
    """`mask` (numpy or torch, [H, W]) as a bool array; ValueError naming `what` on another shape."""
    m = np.asarray(mask.detach().cpu() if hasattr(mask, "detach") else mask)
    if m.shape != (H, W):
        raise ValueError(f"{what}: mask is {m.shape} but the camera is {H}x{W} (rows x columns)")
    return m.astype(bool)


def bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(H, W) bool -> (y0, y1, x0, x1) half-open bounding box of the True pixels, None if empty."""
    ys = np.flatnonzero(mask.any(axis=1))
    if len(ys) == 0:
        return None
    xs = np.flatnonzero(mask.any(axis=0))
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1


def bbox_mask(mask: np.ndarray, pad: int = 0) -> np.ndarray:
    """The enclosing axis-aligned box of a mask, grown by `pad` pixels: (H, W) bool."""
    out = np.zeros_like(mask, dtype=bool)
    b = bbox(mask)
    if b is None:
        return out
    y0, y1, x0, x1 = b
    H, W = mask.shape
    out[max(0, y0 - pad) : min(H, y1 + pad), max(0, x0 - pad) : min(W, x1 + pad)] = True
    return out


# The ring a training mask needs beyond an object's label, as a share of the image's longer side:
# the object's antialiased fringe, its contact shadow and a segmentation's slack lie there, and
# left outside the mask they are trained as background (thin light lines where the box's edges
# were, on the shared SPIn-NeRF scene). SPIn-NeRF's own training masks, for which its LaMa inpaints
# were made, reach that far: the dataset's fills differ from the photos up to 13.6 px (99th
# percentile) beyond the label at 1008 px (1.35 %).
MASK_RING_SHARE = 0.014


def auto_dilation(width: int, height: int) -> int:
    """Iterations of `dilate_mask`'s 5x5 kernel (2 px each) for a ring of MASK_RING_SHARE of the
    longer side, at least 1: 4 (8 px) at 504x284, 1 (2 px) at 192x144."""
    return max(1, round(MASK_RING_SHARE * max(width, height) / 2))


def dilate_mask(mask: np.ndarray, kernel: int = 5, iterations: int = 5) -> np.ndarray:
    """Binary dilation as SPIn-NeRF does (5x5 ones kernel, 5 iterations): (H, W) bool."""
    if iterations <= 0:
        return mask.astype(bool)
    k = np.ones((kernel, kernel), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k, iterations=iterations).astype(bool)


def scribble_mask(
    mask: np.ndarray,
    seed: int = 0,
    n_strokes: int = 4,
    max_width: int | None = None,
    reach: float = 0.6,
) -> np.ndarray:
    """Irregular mask: the segmentation mask plus seeded random brush strokes (paper supp., Fig. R).

    Strokes start inside the mask's bounding box and wander up to `reach` times the box size
    outside it, so the result covers the object and spills irregularly around it. (H, W) bool.
    """
    rng = np.random.default_rng(seed)
    m = mask.astype(bool)
    b = bbox(m)
    H, W = m.shape
    if b is None:
        log.warning("scribble_mask: empty segmentation mask, scribbles start at the image centre")
        b = (H // 2 - 1, H // 2 + 1, W // 2 - 1, W // 2 + 1)
    y0, y1, x0, x1 = b
    size = max(y1 - y0, x1 - x0, 4)
    max_width = max_width or max(3, size // 8)
    canvas = np.zeros((H, W), np.uint8)
    for _ in range(n_strokes):
        x = rng.uniform(x0, x1)
        y = rng.uniform(y0, y1)
        angle = rng.uniform(0, 2 * np.pi)
        width = int(rng.integers(max(2, max_width // 2), max_width + 1))
        for _ in range(int(rng.integers(3, 7))):
            angle += rng.uniform(-1.2, 1.2)
            length = rng.uniform(0.2, 0.5) * size
            nx = np.clip(x + length * np.cos(angle), x0 - reach * size, x1 + reach * size)
            ny = np.clip(y + length * np.sin(angle), y0 - reach * size, y1 + reach * size)
            cv2.line(canvas, (int(x), int(y)), (int(nx), int(ny)), 1, width)
            x, y = nx, ny
    return m | canvas.astype(bool)


def derive_mask(mask: np.ndarray, kind: str = "seg", seed: int = 0, dilate: int = 0) -> np.ndarray:
    """The mask of a given kind ("seg", "bbox", "scribble") from a segmentation mask, optionally
    dilated `dilate` iterations with SPIn-NeRF's 5x5 kernel. (H, W) bool."""
    if kind == "seg":
        out = mask.astype(bool)
    elif kind == "bbox":
        out = bbox_mask(mask)
    elif kind == "scribble":
        out = scribble_mask(mask, seed=seed)
    else:
        raise ValueError(f"unknown mask kind {kind!r}; use one of {MASK_KINDS}")
    return dilate_mask(out, iterations=dilate) if dilate else out


def write_mask(path: str | Path, mask: np.ndarray, value: int = 1) -> None:
    """Write (H, W) bool as an 8-bit PNG with 0 / `value` (SPIn-NeRF uses 1), atomically."""
    from .io import write_png

    write_png(path, mask.astype(np.uint8) * np.uint8(value))
