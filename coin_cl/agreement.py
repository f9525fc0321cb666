"""Cross-view agreement of per-view fills: do the views say the same thing about the hole?

Each training view's fill (a stage-1 inpaint, a CLG image, a render) is carried into its nearest
views through a depth map (the coarse model's, or the truth on a synthetic scene): a pixel p of view j
inside j's region, at camera z `depths[j][p]`, is unprojected, projected into view i and compared with
the pixel q it lands in when q lies in i's region too and i's own depth there agrees with the
projected z (`depth_tol`, relative: q sees the same surface, not an occluder). The disagreement is
the mean absolute RGB difference (in [0, 1]) over those pixels; the coverage is their share of j's
region. Views that agree by construction (renders of one 3D model) show the ruler's own floor
(geometry error, view-dependent colour, nearest-pixel sampling); per-view fills that disagree show
it above that floor.

Pure numpy on the cameras' own projection (`Camera.project` / `unproject`), no OpenCL: it reads
a run's files and is cheap next to any stage (a pair of 400x300 views takes milliseconds).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

# A pixel of view i sees the carried point when i's depth there is within this fraction of the
# point's camera z (the same tolerance scale as the warp kernel's occlusion test).
DEPTH_TOL = 0.05
# Each view is compared with this many nearest views (camera centres): warps between neighbours
# are the reliable ones, and a pair of distant views rarely sees the same part of a hole.
NEIGHBOURS = 2


@dataclass(frozen=True)
class PairAgreement:
    """View `dst`'s region compared with view `src` through the depth: `pixels` compared,
    `coverage` = pixels / dst's region area, `disagreement` = mean |dst - src| RGB in [0, 1]
    (NaN when no pixel could be compared)."""

    dst: int
    src: int
    pixels: int
    coverage: float
    disagreement: float


def neighbour_pairs(cameras: Sequence[Any], k: int = NEIGHBOURS) -> list[tuple[int, int]]:
    """(dst, src) index pairs: every camera with its `k` nearest other cameras by centre distance
    (ties by index). Fewer than two cameras give none."""
    c = np.stack([np.asarray(cam.center, np.float64) for cam in cameras]) if cameras else np.zeros((0, 3))
    pairs = []
    for j in range(len(c)):
        d = np.linalg.norm(c - c[j], axis=1)
        d[j] = np.inf
        order = np.argsort(d, kind="stable")[: min(k, len(c) - 1)]
        pairs += [(j, int(i)) for i in order if np.isfinite(d[i])]
    return pairs


def carried(cam_dst: Any, cam_src: Any, img_src: np.ndarray, region_dst: np.ndarray,
            region_src: np.ndarray, depth_dst: np.ndarray, depth_src: np.ndarray,
            depth_tol: float = DEPTH_TOL) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """View src's image carried into view dst's region (module doc): ([H, W, 3] float64 in [0, 1],
    zero where nothing was carried; [H, W] bool, the pixels carried). img_src: [H', W', 3] in
    [0, 1] (uint8 is scaled); region_*: bool; depth_*: camera z (non-finite or <= 0: unknown)."""
    region_dst = np.asarray(region_dst, bool)
    H, W = region_dst.shape
    warped, valid = np.zeros((H, W, 3)), np.zeros((H, W), bool)
    rows, cols = np.nonzero(region_dst)
    z = np.asarray(depth_dst, np.float64)[rows, cols]
    known = np.isfinite(z) & (z > 0)
    rows, cols, z = rows[known], cols[known], z[known]
    if len(z) == 0:
        return warped, valid
    pts = cam_dst.unproject(np.stack([cols + 0.5, rows + 0.5], 1), z)
    px, ok = cam_src.pixels(pts)  # in front of src, finite, inside its image
    zs = cam_src.project(pts)[1]
    qu, qv = px[:, 0], px[:, 1]
    d_src = np.asarray(depth_src, np.float64)[qv, qu]
    with np.errstate(invalid="ignore"):
        ok &= np.asarray(region_src, bool)[qv, qu] & np.isfinite(d_src) & (d_src > 0)
        ok &= np.abs(d_src - zs) <= depth_tol * np.abs(zs)
    warped[rows[ok], cols[ok]] = _unit(img_src)[qv[ok], qu[ok]]
    valid[rows[ok], cols[ok]] = True
    return warped, valid


def pair_agreement(cam_dst: Any, cam_src: Any, img_dst: np.ndarray, img_src: np.ndarray,
                   region_dst: np.ndarray, region_src: np.ndarray, depth_dst: np.ndarray,
                   depth_src: np.ndarray, depth_tol: float = DEPTH_TOL
                   ) -> tuple[int, float, float]:  # fmt: skip
    """(pixels, coverage, disagreement) of view dst's region against view src (module doc; the
    arguments as `carried`'s, img_dst like img_src). An empty region, or one where nothing could be
    carried, gives (0, 0.0, NaN)."""
    area = int(np.asarray(region_dst, bool).sum())
    warped, valid = carried(
        cam_dst, cam_src, img_src, region_dst, region_src, depth_dst, depth_src, depth_tol
    )
    n = int(valid.sum())
    if n == 0:
        return 0, 0.0, float("nan")
    return n, n / area, float(np.abs(_unit(img_dst)[valid] - warped[valid]).mean())


def cross_view_agreement(cameras: Sequence[Any], images: Sequence[np.ndarray], regions: Sequence[np.ndarray],
                         depths: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]] | None = None,
                         depth_tol: float = DEPTH_TOL
                         ) -> tuple[list[PairAgreement], dict[str, float]]:  # fmt: skip
    """Every pair's `PairAgreement` (default pairs: `neighbour_pairs(cameras)`) and the summary
    {"disagreement": pixel-weighted mean over the pairs (NaN when none compared a pixel),
    "coverage": mean coverage, "pairs": pairs compared, "pixels": pixels compared}."""
    n = len(cameras)
    if not (len(images) == len(regions) == len(depths) == n):
        raise ValueError(
            f"cross_view_agreement: {n} cameras but {len(images)} images, {len(regions)} regions and "
            f"{len(depths)} depth maps; give one of each per view"
        )
    out = []
    for j, i in neighbour_pairs(cameras) if pairs is None else pairs:
        px, cov, dis = pair_agreement(cameras[j], cameras[i], images[j], images[i], regions[j], regions[i],
                                      depths[j], depths[i], depth_tol)  # fmt: skip
        out.append(PairAgreement(j, i, px, cov, dis))
    compared = [p for p in out if p.pixels > 0]
    total = sum(p.pixels for p in compared)
    summary = {
        "disagreement": float(sum(p.disagreement * p.pixels for p in compared) / total)
        if total
        else float("nan"),
        "coverage": float(np.mean([p.coverage for p in out])) if out else 0.0,
        "pairs": len(compared),
        "pixels": int(total),
    }
    return out, summary


def _unit(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img)
    a = a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)
    return np.nan_to_num(a[..., :3], nan=0.0, posinf=1.0, neginf=0.0)
