"""FSR's structure with each surface's colour made smooth: the smooth solver "fsr_surfaces".

FSR (frequency-selective reconstruction) continues the lines that enter a hole (a desk's edge
against a wall) but, far inside a large hole, also draws colours its surroundings do not have (green
tints, blotches). A harmonic fill of the colour has no tints but no edges either: across a desk's
edge it greys the wood with the wall. This solver keeps FSR's luminance and FSR's decision of where
each surface lies, and makes the colour (YCrCb's chroma) harmonic inside each surface separately:

1. the hole's ring (known pixels within `SurfaceChromaConfig.ring_px`) is split into at most two
   colour clusters (2-means in YCrCb); two only when their centres lie `min_sep` apart and the
   smaller holds `min_share` of the ring, else one. Luminance takes part so that a tint FSR draws
   far inside (a green band on wood) joins the surface of its brightness, not the nearest chroma of
   another object (a white cup's grey); a surface split in two by a shadow costs nothing, since both
   halves keep their own, equal chroma;
2. every hole pixel takes the cluster nearest to FSR's colour there (blurred by `label_sigma`, so
   FSR's small tints do not form surfaces of their own), every ring pixel the cluster nearest to its
   own colour;
3. the chroma of each hole pixel solves Laplace's equation over its own cluster's pixels: neighbours
   of the same cluster are coupled (known ones are boundary values), neighbours of the other cluster
   are not (no flux across a surface's edge). A screening term of weight `screen` towards FSR's
   chroma keeps a region that touches no known pixel of its cluster solvable (it then takes about
   FSR's mean colour there).

What it gives up: colour that varies within one surface, which FSR continues and this solver
flattens (a multicoloured periodic pattern: FSR's fill 39.6 dB, this one 14.4 dB). Hence an option
of `ExemplarConfig.structure` for surfaces of one colour each (wood, walls, floors), measured on the
cup scenes in docs/BENCHMARKS.md ("FSR with each surface's colour made harmonic").

Images (H, W, 3) float [0, 1]; masks (H, W) bool, True = hole. Pure numpy, OpenCV and scipy.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .inpaint2d import check_image_mask
from .poisson import screened_solve


@dataclass(frozen=True)
class SurfaceChromaConfig:
    """Settings of `surface_chroma`; the module docstring says where each one acts."""

    # Known pixels within this many pixels of the hole form the ring whose colours are clustered.
    ring_px: int = 7
    # The two clusters' centres must lie at least this far apart (Y, Cr, Cb distance in [0, 1] units;
    # 0.03 is about 8 of 255 levels) for the ring to count as two surfaces.
    min_sep: float = 0.03
    # ... and the smaller cluster must hold at least this share of the ring's pixels.
    min_share: float = 0.15
    # Gaussian sigma (pixels) of FSR's colour before hole pixels are assigned to a cluster.
    label_sigma: float = 2.0
    # Weight of the pull towards FSR's chroma, against the Laplacian's 4 per pixel: small against the
    # coupling across a 200 px hole (~1/200^2), so it decides only where no boundary value reaches.
    screen: float = 1e-6


def two_means(x: np.ndarray, iters: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic 2-means of x (N, D): centres started at the 10th and 90th percentiles of the
    projection on the first principal axis. Returns (centres (2, D), labels (N,) int)."""
    mu = x.mean(0)
    d = x - mu
    _, _, vt = np.linalg.svd(d, full_matrices=False)
    proj = d @ vt[0]
    lo, hi = np.percentile(proj, [10, 90])
    centres = np.stack([x[np.argmin(np.abs(proj - lo))], x[np.argmin(np.abs(proj - hi))]]).astype(np.float64)
    labels = np.zeros(len(x), np.int64)
    for _ in range(iters):
        labels = np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(-1), 1)
        new = np.stack([x[labels == k].mean(0) if (labels == k).any() else centres[k] for k in range(2)])
        if np.allclose(new, centres):
            break
        centres = new
    return centres, labels


def ring_clusters(colour: np.ndarray, ring: np.ndarray, cfg: SurfaceChromaConfig) -> np.ndarray:
    """The ring's surface colours: (K, C) centres of `colour` (H, W, C) over `ring` (H, W) bool,
    K = 1 or 2 (module docstring, step 1)."""
    x = colour[ring].astype(np.float64)
    if len(x) < 8:
        return x.mean(0, keepdims=True) if len(x) else np.full((1, colour.shape[-1]), 0.5)
    centres, labels = two_means(x)
    share = min((labels == 0).mean(), (labels == 1).mean())
    if np.linalg.norm(centres[0] - centres[1]) >= cfg.min_sep and share >= cfg.min_share:
        return centres
    return x.mean(0, keepdims=True)


def _nearest(colour: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(H, W) index of the centre (K, C) nearest to each pixel of colour (H, W, C)."""
    return np.argmin(((colour[..., None, :] - centres) ** 2).sum(-1), -1)


def surface_chroma(
    image: np.ndarray, hole: np.ndarray, fsr: np.ndarray, cfg: SurfaceChromaConfig | None = None
) -> np.ndarray:
    """`fsr` (the image with FSR's fill of `hole`) with the hole's chroma made harmonic per surface
    (module docstring). image, fsr (H, W, 3) float [0, 1]; hole (H, W) bool. Returns (H, W, 3)
    float32 in [0, 1], equal to `image` outside the hole. Each connected part of the hole has its own
    ring, clusters and solve. Raises ValueError on shapes that disagree or NaN/Inf in `image` or `fsr`."""
    cfg = cfg or SurfaceChromaConfig()
    image, hole = check_image_mask(image, hole)
    fsr, _ = check_image_mask(fsr, hole)
    out = np.asarray(fsr, np.float32).copy()
    out[~hole] = np.asarray(image, np.float32)[~hole]
    if not hole.any() or hole.all():
        return out
    ycc = cv2.cvtColor(out, cv2.COLOR_RGB2YCrCb)
    colour = ycc.astype(np.float64)
    chroma = colour[..., 1:]
    smooth = cv2.GaussianBlur(colour, (0, 0), cfg.label_sigma) if cfg.label_sigma > 0 else colour
    n_parts, parts = cv2.connectedComponents(hole.astype(np.uint8), connectivity=4)
    near = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 3) <= cfg.ring_px
    box = np.ones((2 * cfg.ring_px + 1,) * 2, np.uint8)
    solved = chroma.copy()
    for k in range(1, n_parts):
        part = parts == k
        ring = (cv2.dilate(part.astype(np.uint8), box) > 0) & near & ~hole
        centres = ring_clusters(colour, ring, cfg)
        label = np.full(hole.shape, -1, np.int64)  # -1: coupled to nothing (other parts, far pixels)
        label[ring] = _nearest(colour, centres)[ring]
        label[part] = _nearest(smooth, centres)[part]
        fill = screened_solve(chroma, part, target=chroma, labels=label, cut=True, screen=cfg.screen)
        solved[part] = fill[part]
    ycc[..., 1:][hole] = solved[hole].astype(np.float32)
    rgb = cv2.cvtColor(ycc, cv2.COLOR_YCrCb2RGB)
    out[hole] = np.clip(rgb[hole], 0.0, 1.0)
    return out
