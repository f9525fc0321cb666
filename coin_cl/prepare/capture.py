"""A capture to try `coin-cl prepare` on without a camera: photos of the synthetic room
(`coin_cl.scene.synthetic`) from known cameras, with the object's true mask in each.

Every face shows its texture once, stretched (the room's default tiles brick and gravel, whose
repeats give structure from motion false matches and, now and then, a wrong model); the tests and
`examples/prepare_and_run.py` use it as ground truth for `run_sfm` and the masks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scene.io import write_png
from ..scene.synthetic import Material, arc_cameras, default_room, render_view
from ..scene.types import Camera


@dataclass
class Capture:
    """photos: the written files; cameras: their true cameras (names = file names); masks: per
    photo (H, W) bool, the object's true footprint."""

    photos: list[Path]
    cameras: list[Camera]
    masks: list[np.ndarray]


def synthetic_capture(folder: str | Path, n_views: int = 12, width: int = 256, height: int = 192,
                      coverage: int = 90, seed: int = 0, supersample: int = 2) -> Capture:  # fmt: skip
    """Render the room with its object from `n_views` cameras on a `coverage`-degree arc into
    `folder` as view_000.png ...; returns the photos, the true cameras and masks."""
    boxes = default_room(seed)
    for b in boxes:
        b.faces = [Material(f.texture, f.tint, None) for f in b.faces]
    obj = next(b for b in boxes if b.is_object)
    cams = arc_cameras(n_views, coverage, width, height, obj.center, seed)
    folder = Path(folder)
    photos, masks = [], []
    for i, cam in enumerate(cams):
        cam.name = f"view_{i:03d}.png"
        r = render_view(boxes, cam, supersample)
        write_png(folder / cam.name, r["present"])
        photos.append(folder / cam.name)
        masks.append(r["mask"])
    return Capture(photos, cams, masks)
