"""Image reading and writing shared by the scene modules (writes are atomic: `coin_cl.atomic`)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from coin_cl.atomic import atomic_write, write_text  # noqa: F401  (re-exported: the scene modules' writers)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")
# The largest image coin-cl decodes, in pixels (width x height): 100 megapixels, above any phone or
# DSLR photo (a 61 MP full-frame sensor is 9504x6336) and ~1.2 GB as float32 RGB. A larger size
# declared in a header is refused before any decode: a 100 KB PNG may declare 12000x12000.
MAX_IMAGE_PIXELS = 100_000_000
# zlib level of every PNG written: 1 wrote a 1008x567 render in 63 ms against 245 ms at PIL's
# default 6, for files 7% larger (1.02 MB against 0.96); an eval stage writes dozens of them.
PNG_COMPRESS_LEVEL = 1


def _unreadable(what: str, path: Path, exc: BaseException) -> ValueError:
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return ValueError(
        f"{what} {path} cannot be read ({msg}): it is truncated or not an image; "
        "replace it (re-export or re-copy it) or remove it from the folder"
    )


def image_header(path: str | Path, what: str = "image") -> tuple[int, int, int]:
    """(width, height, channels) of an image file from its header alone, nothing decoded; a
    ValueError naming the file when it is not an image or declares more than MAX_IMAGE_PIXELS.

    Pillow's `Image.open` is lazy: it parses the header (PNG IHDR, JPEG SOF) and leaves the pixel
    data unread until `load()`, so this costs a few hundred bytes of reading whatever the size the
    file declares. (imageio's `improps` may decode to learn the dtype; OpenCV has no header-only
    read.)"""
    import warnings

    from PIL import Image

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                (w, h), bands = im.size, len(im.getbands())
    except Image.DecompressionBombError:
        w, h, bands = -1, -1, 0  # beyond Pillow's own bound: refused below with ours
    except Image.UnidentifiedImageError as exc:
        if path.suffix in IMAGE_EXTS:
            raise _unreadable(what, path, exc) from None
        # Formats Pillow lacks (float TIFF, EXR): imageio's metadata, which its plugins read
        # from the header for these.
        try:
            shape = iio.improps(path).shape
        except Exception as exc2:  # noqa: BLE001
            raise _unreadable(what, path, exc2) from None
        h, w = (int(shape[0]), int(shape[1])) if len(shape) >= 2 else (0, 0)
        bands = int(shape[2]) if len(shape) > 2 else 1
    except Exception as exc:  # noqa: BLE001 - every format plugin raises its own kind
        raise _unreadable(what, path, exc) from None
    if w < 1 or h < 1 or w * h > MAX_IMAGE_PIXELS:
        size = f"{w}x{h}" if w > 0 else "more than twice that"
        raise ValueError(
            f"{what} {path} declares {size} pixels, more than the {MAX_IMAGE_PIXELS // 10**6} megapixels "
            "coin-cl decodes; downscale it (e.g. `coin-cl prepare --width 1008`) or remove it"
        )
    return w, h, bands


def imread_checked(path: str | Path, what: str = "image") -> np.ndarray:
    """`imageio.imread` with one clear error for a missing, truncated or unreadable file: a
    FileNotFoundError / ValueError naming it and what to do (never a decoder traceback)."""
    path = Path(path)
    image_header(path, what)  # the declared size is checked before anything is decoded
    try:
        a = np.asarray(iio.imread(path))
    except Exception as exc:  # every decoder raises its own kind (OSError, ValueError, SyntaxError...)
        raise _unreadable(what, path, exc) from None
    if a.ndim not in (2, 3) or a.size == 0 or a.dtype.kind not in "uif" or (a.ndim == 3 and a.shape[2] > 4):
        raise ValueError(
            f"{what} {path} is not a single 2D picture (array {a.shape} {a.dtype}); "
            "save it as an 8- or 16-bit PNG or JPEG"
        )
    return a


def read_image(path: str | Path) -> np.ndarray:
    """Read an image -> (H, W, 3) float32 in [0, 1]. Documented handling: grey images are repeated
    into RGB; an alpha channel is dropped (the colour is used as stored, not composited); 16-bit
    images are scaled by 65535, 8-bit by 255 (float images are taken as [0, 1] and clipped).
    A truncated or unreadable file raises ValueError naming it."""
    a = imread_checked(path)
    scale = {np.dtype(np.uint16): 65535.0, np.dtype(np.uint8): 255.0}.get(a.dtype, 1.0)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    elif a.shape[2] < 3:  # grey + alpha
        a = np.repeat(a[..., :1], 3, axis=2)
    a = a[..., :3]
    out = a.astype(np.float32) / np.float32(scale)
    if not np.isfinite(out).all():
        raise ValueError(f"image {path} holds NaN or Inf values; save it as an 8- or 16-bit PNG or JPEG")
    return out.clip(0, 1)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] (or uint8) -> uint8, rounded."""
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write a float [0, 1] or uint8 image (H, W[, 3]) as PNG, atomically (zlib level
    `PNG_COMPRESS_LEVEL`)."""
    data = to_uint8(img)
    atomic_write(path, lambda p: iio.imwrite(p, data, extension=".png", compress_level=PNG_COMPRESS_LEVEL))


def write_npy(path: str | Path, arr: np.ndarray) -> None:
    """np.save atomically."""

    def _w(p: Path) -> None:
        with open(p, "wb") as f:
            np.save(f, arr)

    atomic_write(path, _w)


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_EXTS)


def view_stem(name: str, index: int) -> str:
    """File stem of a view's per-view outputs (renders/<stem>.png, ...): its image name without the
    extension, or view_<index:03d> for a view without a name."""
    return Path(name).stem if name else f"view_{index:03d}"
