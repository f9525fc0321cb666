"""PLY point clouds (x y z [red green blue]): COLMAP's and SPIn-NeRF's sparse points, P_k.
Gaussians in the 3DGS PLY layout are `coin_cl.gs.splats.Splats` (`to_ply` / `from_ply`)."""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from .io import atomic_write

log = logging.getLogger(__name__)


def write_points_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    """Point cloud (N, 3) with optional colours (N, 3) in [0, 1] -> binary PLY (x y z [r g b])."""
    n = len(points)
    dt = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        dt += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    arr = np.empty(n, dtype=dt)
    for i, c in enumerate("xyz"):
        arr[c] = points[:, i]
    if colors is not None:
        c8 = (np.clip(colors, 0, 1) * 255 + 0.5).astype(np.uint8)
        for i, c in enumerate(("red", "green", "blue")):
            arr[c] = c8[:, i]
    el = PlyElement.describe(arr, "vertex")
    atomic_write(path, lambda p: PlyData([el], byte_order="<").write(str(p)))


def read_ply_vertices(path: str | Path, what: str = "PLY") -> np.ndarray:
    """The `vertex` element of a PLY file as a numpy structured array. A file that is truncated,
    not a PLY, or has no vertex element is one ValueError line naming it (plyfile's own errors
    name neither the file nor what to do)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    try:
        ply = PlyData.read(str(path))
        return ply["vertex"].data
    except KeyError:
        raise ValueError(f"{path} has no vertex element; it is not a {what}") from None
    except (PlyParseError, ValueError, EOFError, UnicodeDecodeError, IndexError, struct.error) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(
            f"{path} is not a readable {what} (truncated or malformed: {why}); re-export or re-copy it"
        ) from None


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """PLY point cloud -> points (N, 3) float32, colours (N, 3) float32 in [0, 1] or None.

    Colours that are all zero (COLMAP run with extract_colors=false, as in the shared SPIn-NeRF
    scene) are unknown, not black: returned as None with a log line.
    """
    path = Path(path)
    v = read_ply_vertices(path, "point cloud")
    pts = np.stack([np.asarray(v[c], np.float32) for c in "xyz"], axis=1)
    names = v.dtype.names
    colors = None
    if all(c in names for c in ("red", "green", "blue")):
        c = np.stack([np.asarray(v[k], np.float32) for k in ("red", "green", "blue")], axis=1)
        if not c.any():
            log.info("%s: point colours are all zero; treating them as unknown", path)
        else:
            colors = c / (65535.0 if v["red"].dtype == np.uint16 else 255.0)
    return pts, colors
