"""PLY files: 3DGS Gaussians in the standard layout (what splat viewers read), and point clouds.

3DGS layout, one vertex per Gaussian, all float32: x y z, nx ny nz (zeros), f_dc_0..2 (SH degree-0
coefficients), f_rest_0..3*(K)-1 (higher SH, channel-major: all R coefficients, then G, then B),
opacity (logit), scale_0..2 (log), rot_0..3 (quaternion wxyz, not necessarily normalised).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from .io import atomic_write

log = logging.getLogger(__name__)


@dataclass
class GaussianPly:
    """Gaussians as stored in a 3DGS PLY.

    means (N, 3), sh_dc (N, 3), sh_rest (N, K, 3) (K = 0, 3, 8 or 15), opacities (N,) logits,
    log_scales (N, 3), quats (N, 4) wxyz; all float32.
    """

    means: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    opacities: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray

    def __len__(self) -> int:
        return len(self.means)


def write_gaussians_ply(path: str | Path, g: GaussianPly) -> None:
    """Write Gaussians in the 3DGS layout (binary little-endian), atomically."""
    n = len(g.means)
    rest = np.asarray(g.sh_rest, np.float32).reshape(n, -1, 3)
    k = rest.shape[1]
    cols: list[tuple[str, np.ndarray]] = []
    cols += [(c, g.means[:, i]) for i, c in enumerate("xyz")]
    cols += [(c, np.zeros(n, np.float32)) for c in ("nx", "ny", "nz")]
    cols += [(f"f_dc_{i}", g.sh_dc[:, i]) for i in range(3)]
    # Channel-major, as the 3DGS reference writes features_rest.transpose(1, 2).flatten(1).
    rest_cm = rest.transpose(0, 2, 1).reshape(n, 3 * k)
    cols += [(f"f_rest_{i}", rest_cm[:, i]) for i in range(3 * k)]
    cols += [("opacity", np.asarray(g.opacities).reshape(n))]
    cols += [(f"scale_{i}", g.log_scales[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", g.quats[:, i]) for i in range(4)]
    arr = np.empty(n, dtype=[(name, "<f4") for name, _ in cols])
    for name, v in cols:
        arr[name] = v
    el = PlyElement.describe(arr, "vertex")
    atomic_write(path, lambda p: PlyData([el], byte_order="<").write(str(p)))


def read_gaussians_ply(path: str | Path) -> GaussianPly:
    """Read a 3DGS PLY written by us or by the reference implementation."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Gaussian PLY {path} not found")
    v = PlyData.read(str(path))["vertex"].data
    names = v.dtype.names
    need = ["x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"]
    missing = [n for n in need if n not in names]
    if missing:
        raise ValueError(
            f"{path} is not a 3DGS PLY (missing {missing}); for a point cloud use read_points_ply"
        )

    def stack(prefix: str) -> np.ndarray:
        cols = sorted((n for n in names if n.startswith(prefix)), key=lambda s: int(s.split("_")[-1]))
        return np.stack([np.asarray(v[c], np.float32) for c in cols], axis=1)

    n = len(v)
    rest_names = [c for c in names if c.startswith("f_rest_")]
    if rest_names:
        rest = stack("f_rest_")
        rest = rest.reshape(n, 3, -1).transpose(0, 2, 1).copy()
    else:
        rest = np.zeros((n, 0, 3), np.float32)
    return GaussianPly(
        means=np.stack([np.asarray(v[c], np.float32) for c in "xyz"], axis=1),
        sh_dc=stack("f_dc_"),
        sh_rest=rest,
        opacities=np.asarray(v["opacity"], np.float32),
        log_scales=stack("scale_"),
        quats=stack("rot_"),
    )


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


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """PLY point cloud -> points (N, 3) float32, colours (N, 3) float32 in [0, 1] or None.

    Colours that are all zero (COLMAP run with extract_colors=false, as in the shared SPIn-NeRF
    scene) are unknown, not black: returned as None with a log line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud {path} not found")
    v = PlyData.read(str(path))["vertex"].data
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
