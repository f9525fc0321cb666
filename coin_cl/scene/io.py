"""Image reading and writing shared by the scene modules (writes are atomic: `coin_cl.atomic`)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from coin_cl.atomic import atomic_write, write_text  # noqa: F401  (re-exported: the scene modules' writers)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8/16-bit RGB(A) or grey image -> (H, W, 3) float32 in [0, 1]."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image {path} not found")
    a = iio.imread(path)
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    a = a[..., :3]
    return (a.astype(np.float32) / np.float32(scale)).clip(0, 1)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] (or uint8) -> uint8, rounded."""
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write a float [0, 1] or uint8 image (H, W[, 3]) as PNG, atomically."""
    data = to_uint8(img)
    atomic_write(path, lambda p: iio.imwrite(p, data, extension=".png"))


def write_npy(path: str | Path, arr: np.ndarray) -> None:
    """np.save atomically."""

    def _w(p: Path) -> None:
        with open(p, "wb") as f:
            np.save(f, arr)

    atomic_write(path, _w)


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_EXTS)
