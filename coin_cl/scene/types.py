"""`Camera` and `Scene`: what every loader returns and every stage consumes."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .conventions import invert_rigid, scale_intrinsics

log = logging.getLogger(__name__)


@dataclass
class Camera:
    """A pinhole camera in the engine's convention (see `conventions`): the one camera type of
    coin-cl (scenes, training views, pipeline stages, CLI and tests).

    K: (3, 3) float64 intrinsics in pixels of (width, height), pixel centres at +0.5.
    viewmat: (4, 4) float64 world-to-camera, OpenCV axes (x right, y down, z forward).
    Stored in float64 numpy (poses of huge scenes keep their precision); the `_t` properties give
    float32 torch tensors for the renderer (`K_t`, `viewmat_t`, `center_t`, `camtoworld_t`).
    Constructing from torch tensors works too (they are converted).
    """

    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.viewmat = np.asarray(self.viewmat, dtype=np.float64).reshape(4, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def camtoworld(self) -> np.ndarray:
        """(4, 4) camera-to-world, OpenCV axes."""
        return invert_rigid(self.viewmat)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.camtoworld[:3, 3]

    @property
    def viewmat_t(self):
        """(4, 4) torch float32 world-to-camera."""
        import torch

        return torch.as_tensor(self.viewmat, dtype=torch.float32)

    @property
    def K_t(self):
        """(3, 3) torch float32 intrinsics."""
        import torch

        return torch.as_tensor(self.K, dtype=torch.float32)

    @property
    def center_t(self):
        """(3,) torch float32 camera centre in world coordinates."""
        import torch

        return torch.as_tensor(self.center, dtype=torch.float32)

    @staticmethod
    def from_any(cam: Any, name: str = "") -> Camera:
        """A copy of any object with K, viewmat, width, height (numpy or torch); its own name
        wins over `name`."""

        def arr(x: Any) -> np.ndarray:
            return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)

        return Camera(arr(cam.K), arr(cam.viewmat), int(cam.width), int(cam.height),
                      str(getattr(cam, "name", "") or name))  # fmt: skip

    def to_json(self) -> dict[str, Any]:
        """{"name", "width", "height", "K", "viewmat"} with plain lists (float64 kept exactly)."""
        return {"name": self.name, "width": self.width, "height": self.height,
                "K": self.K.tolist(), "viewmat": self.viewmat.tolist()}  # fmt: skip

    @staticmethod
    def from_json(d: dict[str, Any]) -> Camera:
        """The inverse of `to_json` (extra keys ignored)."""
        return Camera(np.array(d["K"]), np.array(d["viewmat"]), d["width"], d["height"], d.get("name", ""))

    @property
    def camtoworld_t(self):
        """(4, 4) torch float32 camera-to-world."""
        import torch

        return torch.as_tensor(self.camtoworld, dtype=torch.float32)

    def torch(self):
        """(viewmat (4, 4), K (3, 3)) as torch float32 tensors."""
        return self.viewmat_t, self.K_t

    def project(self, points: Any, near: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) (numpy or torch) -> pixel coordinates (N, 2) in our convention and
        camera z (N,), in float64.

        Points at z <= near get NaN coordinates: near 0 (default) drops what is behind the camera;
        the renderer's near plane (`engine.constants.NEAR_PLANE`) keeps exactly what it could draw.
        """
        pts = np.asarray(points.detach().cpu() if hasattr(points, "detach") else points, dtype=np.float64)
        pts = pts.reshape(-1, 3)
        pc = pts @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (pc[:, :2] / z[:, None]) @ self.K[:2, :2].T + self.K[:2, 2]
        uv[~(z > near)] = np.nan  # also NaN z
        return uv, z

    def pixels(self, points: Any, near: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The pixels world points (N, 3) fall in.

        Returns (px (N, 2) int64 (column, row), ok (N,) bool): ok = z > near and the projection is
        finite and inside the image; px is only meaningful where ok (0 elsewhere). Pixel centres
        are at +0.5, so (u, v) lies in pixel (floor(v), floor(u)).
        """
        uv, _ = self.project(points, near)
        ok = self.in_image(uv) & np.isfinite(uv).all(1)
        px = np.zeros((len(uv), 2), np.int64)
        px[ok] = np.floor(uv[ok]).astype(np.int64)
        # floor(u) can equal W only through rounding at the border; keep the index valid.
        px[:, 0] = np.clip(px[:, 0], 0, self.width - 1)
        px[:, 1] = np.clip(px[:, 1], 0, self.height - 1)
        return px, ok

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) and camera z (N,) -> world points (N, 3)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        d = np.asarray(depth, dtype=np.float64).reshape(-1)
        x = (uv[:, 0] - self.K[0, 2]) / self.K[0, 0]
        y = (uv[:, 1] - self.K[1, 2]) / self.K[1, 1]
        pc = np.stack([x * d, y * d, d], axis=1)
        c2w = self.camtoworld
        return pc @ c2w[:3, :3].T + c2w[:3, 3]

    def rays(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """World directions (N, 3), scaled to camera z = 1, through pixel coordinates (xs, ys) (N,)."""
        uv = np.stack([np.asarray(xs, np.float64).reshape(-1), np.asarray(ys, np.float64).reshape(-1)], 1)
        return self.unproject(uv, np.ones(len(uv))) - self.center

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates -> (N,) bool, inside [0, W) x [0, H)."""
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to (width, height)."""
        K = scale_intrinsics(self.K, width / self.width, height / self.height)
        return replace(self, K=K, width=width, height=height)


@dataclass
class Scene:
    """A posed image collection with object masks.

    images: per view (H, W, 3) float32 in [0, 1]; masks: per view (H, W) bool, True = object /
    region to inpaint (all False where none was given; for test views the region to score).
    points: (N, 3) float32 sparse points; colors: (N, 3) float32 in [0, 1] or None when unknown.
    priors: {"rgb": {view: (H, W, 3) float32}, "depth": {view: (H, W) float32 disparity in [0, 1]}}
    extras: optional per-view data a source ships ({"depth": {view: (H, W) float32 camera z}, ...}).
    near, far: (n_views,) float64 depth bounds when known.
    """

    cameras: list[Camera]
    images: list[np.ndarray]
    masks: list[np.ndarray]
    points: np.ndarray
    colors: np.ndarray | None = None
    train_idx: list[int] = field(default_factory=list)
    test_idx: list[int] = field(default_factory=list)
    priors: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    extras: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    ref_view: int | None = None
    near: np.ndarray | None = None
    far: np.ndarray | None = None
    path: Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        """View index of an image name (with or without extension)."""
        for i, c in enumerate(self.cameras):
            if c.name == name or Path(c.name).stem == Path(name).stem:
                return i
        raise KeyError(f"no view named {name!r} in scene {self.path}")

    def resized(self, resolution: float) -> Scene:
        """A copy with images, masks and priors resized by `resolution` (0.5 -> half size).

        Images use area averaging; masks are conservative (`resize_mask`: any pixel the object covers
        even partly stays masked, so no mixed object colour is left outside the mask).
        """
        if resolution == 1.0:
            return self
        if not 0 < resolution <= 1.0:
            raise ValueError(f"resolution must be in (0, 1], got {resolution}")
        cams, imgs, masks = [], [], []
        for cam, img, m in zip(self.cameras, self.images, self.masks, strict=True):
            w = max(1, round(cam.width * resolution))
            h = max(1, round(cam.height * resolution))
            cams.append(cam.resized(w, h))
            imgs.append(resize_image(img, w, h))
            masks.append(resize_mask(m, w, h))

        def _resize_dict(d: dict[int, np.ndarray], nearest: bool = False) -> dict[int, np.ndarray]:
            out = {}
            for i, a in d.items():
                w, h = cams[i].width, cams[i].height
                out[i] = resize_mask(a, w, h) if a.dtype == bool else resize_image(a, w, h)
            return out

        return replace(
            self,
            cameras=cams,
            images=imgs,
            masks=masks,
            priors={k: _resize_dict(v) for k, v in self.priors.items()},
            extras={k: _resize_dict(v) for k, v in self.extras.items()},
            meta={**self.meta, "resolution": resolution * self.meta.get("resolution", 1.0)},
        )


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W[, C]) float image -> (height, width[, C]); INTER_AREA when shrinking."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    interp = cv2.INTER_AREA if width < img.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(img, (width, height), interpolation=interp)


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool -> (height, width) bool, conservative: shrinking, a pixel is masked when any part of
    it is (area average > 0), since an area-resized image mixes the object's colours into it;
    enlarging, nearest neighbour (each pixel lies in one source pixel)."""
    if mask.shape[1] == width and mask.shape[0] == height:
        return mask
    if width < mask.shape[1] or height < mask.shape[0]:
        return cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) > 0
    out = cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
    return out.astype(bool)
