"""Training views as the trainer sees them, and the bridge from a loaded `Scene`.

A `View` is one camera with its target image, an optional exclusion mask and a loss weight. The
trainer never looks at the scene loader's types; `views_from_scene` duck-types them (anything with
`cameras[i].K/.viewmat/.width/.height`, `images`, optional `masks`); `init_points` gives the
scene's sparse points and colours a model starts from.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from coin_cl.scene.types import Camera


@dataclass
class View:
    """One training/evaluation view: camera, target image [H, W, 3] float32 in [0, 1],
    `exclude` [H, W] bool (True = pixel not used by the loss) or None, and a loss weight."""

    camera: Camera
    image: Tensor
    exclude: Tensor | None = None
    weight: float = 1.0
    meta: dict = field(default_factory=dict)


def views_from_scene(
    scene,
    indices: Sequence[int],
    images: Sequence | None = None,
    exclude_masks: bool = False,
) -> list[View]:
    """Views for the given scene indices.

    Args:
        scene: a loaded scene (cameras, images, optional masks).
        indices: which views.
        images: replacement targets aligned with `scene.images` (e.g. per-view inpaints);
            default the scene's own images.
        exclude_masks: leave each view's object mask out of the loss.
    """
    imgs = scene.images if images is None else images
    masks = getattr(scene, "masks", None)
    out = []
    for i in indices:
        cam = Camera.from_any(scene.cameras[i], name=str(i))
        img = torch.as_tensor(np.asarray(imgs[i], dtype=np.float32))
        if tuple(img.shape[:2]) != (cam.height, cam.width):
            raise ValueError(
                f"view {i}: image {tuple(img.shape)} does not match camera {cam.width}x{cam.height}"
            )
        ex = None
        if exclude_masks and masks is not None and masks[i] is not None:
            ex = torch.as_tensor(np.asarray(masks[i], dtype=bool))
        out.append(View(cam, img[..., :3].contiguous(), ex))
    return out


def colors_from_views(points: np.ndarray, views: Sequence[View], max_views: int = 8) -> np.ndarray:
    """Colour SfM points by projecting them into a few views and averaging the pixels they hit.

    Needed when the capture's points carry no colour (SPIn-NeRF's COLMAP ran without it); a
    point seen by no sampled view gets mid-grey.

    Args:
        points: [N, 3] world positions.
    Returns:
        [N, 3] float32 colours in [0, 1].
    """
    pts = torch.as_tensor(points, dtype=torch.float32)
    acc = torch.zeros(len(pts), 3)
    cnt = torch.zeros(len(pts))
    step = max(1, len(views) // max_views)
    for v in list(views)[::step][:max_views]:
        c = v.camera
        V, K = c.viewmat_t, c.K_t
        pc = pts @ V[:3, :3].T + V[:3, 3]
        z = pc[:, 2]
        uv = pc[:, :2] / z.clamp_min(1e-6)[:, None] @ K[:2, :2].T + K[:2, 2]
        px = torch.floor(uv).long()
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < c.width) & (px[:, 1] >= 0) & (px[:, 1] < c.height)
        if v.exclude is not None:
            ok[ok.clone()] &= ~v.exclude[px[ok, 1], px[ok, 0]]
        acc[ok] += v.image[px[ok, 1], px[ok, 0]]
        cnt[ok] += 1
    col = torch.where(cnt[:, None] > 0, acc / cnt.clamp_min(1)[:, None], torch.full_like(acc, 0.5))
    return col.numpy()


def init_points(scene, views: Sequence[View]) -> tuple[np.ndarray, np.ndarray]:
    """The scene's sparse points [N, 3] and colours [N, 3] (float32), colouring the points from
    `views` (`colors_from_views`) when the scene has no colours; a model is built from them."""
    pts = np.asarray(scene.points, dtype=np.float32)
    cols = scene.colors
    if cols is None:
        cols = colors_from_views(pts, views)
    return pts, np.asarray(cols, dtype=np.float32)


def scene_extent(cameras: Sequence[Camera]) -> float:
    """3DGS' 'cameras_extent': 1.1 x the largest camera distance from the mean centre."""
    cs = torch.stack([c.center_t for c in cameras])
    r = (cs - cs.mean(0)).norm(dim=-1).max().item()
    return 1.1 * max(r, 1e-6)
