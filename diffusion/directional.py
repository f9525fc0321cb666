"""Grain-following texture for a hole: the surroundings' fine band carried straight through it.

Many surfaces a removal uncovers carry an oriented texture whose lines run on under the object: a
desk's or floor's wood grain, brushed metal, fabric. A patch synthesis puts copies of that texture
in the hole in arbitrary places; a smooth fill drops it. Here, where the known pixels around a hole
share one dominant orientation, every hole pixel takes the high band of the pixels where its line
through the hole, along that orientation, meets the surroundings on either side, the two sides
weighted by nearness (the line's value interpolated across the hole). Colour and shading come from
the smooth structure fill the band is added to (`diffusion.exemplar`), so a lighting gradient across
the hole is not streaked along the lines.

What it does and does not do, measured (docs/BENCHMARKS.md, "Grain transport"): straight lines (a
painted line, an edge, synthetic grain) leave the hole where their continuation is, in phase. On
real wood grain (cup_plain at 400x300) the band at sigma 2 px is not predictable along the grain at
the hole's scale (its correlation with itself half a hole further along the dominant orientation is
about 0), so what arrives in the hole is streaks at the grain's orientation with the surroundings'
texture, not the true lines. On textures with no true orientation but a coherent ring (SPIn-NeRF's
gravel and leaves beside a bench edge, ring coherence 0.4-0.5) it draws streaks that are not there;
hence off by default (`ExemplarConfig.grain`).

The orientation (`ring_orientation`): the structure tensor of the ring's luminance (Sobel gradients,
smoothed over `rho` px), each ring pixel voting its local orientation with its local coherence as
weight; the votes' mean resultant length on doubled angles (in [0, 1]) is the ring's coherence. A
pixel is one vote whatever its contrast, so an object's strong edge in the ring (a cup beside the
hole) does not outvote a faint grain around it. Below `min_coherence` (isotropic texture, two
crossing sets of lines such as tile joints, noise) nothing is transported and the caller keeps its
own texture.

Sampling never reaches into the hole or its edge: the band of the known pixels is their difference
to a Gaussian mean of known pixels only (normalised convolution), and samples start `guard_px`
outside the hole. A line whose two ends disagree in colour by more than `mismatch` robust deviations
of the ring crosses from one surface to another (it meets a cup beside the hole on one side): it
takes the end nearer the ring's median colour alone. A line parallel to an edge has both ends on the
same side of it and keeps both. A line that leaves the image on both sides gets no band (the
structure fill alone).

Pure numpy + OpenCV, deterministic. Images (H, W, 3) float32 [0, 1]; holes (H, W) bool, True = fill.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .inpaint2d import check_image_mask

LUMA = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601 weights: the tensor's luminance


@dataclass(frozen=True)
class DirectionalConfig:
    """Settings of the grain transport; each field says what it means where it is declared."""

    # Coherence (mean resultant length of the ring's orientation votes, [0, 1]) from which a hole's
    # surroundings count as oriented. Measured (benchmarks/grain.py, inpaint2d.py): cup_plain's 56
    # holes in wood grain 0.40-0.98 (one on the cup's white rim 0.04); SPIn-NeRF's holes in gravel,
    # leaves and bench edges 0.15-0.74. It does not tell grain from gravel: hence the option is off.
    min_coherence: float = 0.3
    # Gaussian sigma (px) splitting the transported high band from the low one (the structure
    # fill's). The exemplar inpainter passes its own `hf_sigma`, so both textures share one band.
    sigma: float = 2.0
    # Gaussian sigma (px) of the structure tensor's smoothing: the scale of one orientation vote.
    rho: float = 3.0
    # Samples averaged along the line past the point where it leaves the hole (1 px apart): the
    # band along a grain line is nearly constant, so this averages noise, not texture.
    samples: int = 3
    # Known pixels closer than this (px) to the hole are neither sampled nor voted with: at the
    # working resolution the mask's edge pixels may hold part of the object.
    guard_px: float = 1.5
    # A line's two ends whose colours differ by more than this many robust deviations of the ring
    # (1.4826 MAD per channel, plus 0.01) lie on two surfaces: the end nearer the ring's median
    # colour is taken alone.
    mismatch: float = 5.0

    def __post_init__(self) -> None:
        for name, ok, what in (
            ("min_coherence", 0.0 <= self.min_coherence <= 1.0, "in [0, 1]"),
            ("sigma", math.isfinite(self.sigma) and self.sigma > 0, "a finite number > 0"),
            ("rho", math.isfinite(self.rho) and self.rho > 0, "a finite number > 0"),
            ("samples", isinstance(self.samples, int) and self.samples >= 1, "an integer >= 1"),
            ("guard_px", math.isfinite(self.guard_px) and self.guard_px >= 1.0, "a finite number >= 1"),
            ("mismatch", math.isfinite(self.mismatch) and self.mismatch > 0, "a finite number > 0"),
        ):
            if not ok:
                raise ValueError(f"DirectionalConfig.{name} is {getattr(self, name)!r}: give {what}")


@dataclass(frozen=True)
class RingOrientation:
    """A hole's surroundings: `direction` (dx, dy) a unit vector along the lines (image x right, y
    down), `coherence` in [0, 1], and the ring's colour `median` (3,) and robust `spread` (3,)."""

    direction: tuple[float, float]
    coherence: float
    median: np.ndarray
    spread: np.ndarray


def ring_reach(component: np.ndarray) -> float:
    """How far (px) around a hole's part its ring reaches: half the part's shorter side, at least 8;
    also the distance the transport bridges from the ring to the part's middle."""
    ys, xs = np.nonzero(component)
    return max(8.0, 0.5 * min(np.ptp(ys) + 1, np.ptp(xs) + 1))


def ring_orientation(
    image: np.ndarray, hole: np.ndarray, component: np.ndarray, cfg: DirectionalConfig
) -> RingOrientation | None:
    """The dominant orientation of the known pixels around `component` (a part of `hole`, both
    (H, W) bool), within `ring_reach` beyond the guard and the tensor's reach (module docstring).
    None when fewer than 16 known pixels lie that far from every hole (a thin strip between holes, a
    hole covering nearly everything): too little to judge."""
    reach = ring_reach(component)
    dist = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 5)
    to_comp = cv2.distanceTransform((~component).astype(np.uint8), cv2.DIST_L2, 5)
    margin = cfg.guard_px + 2 * cfg.rho  # the tensor there is mostly the known pixels'
    ring = (dist > margin) & (to_comp <= reach + margin)
    if ring.sum() < 16:
        return None
    colours = image[ring]
    median = np.median(colours, 0).astype(np.float32)
    spread = (1.4826 * np.median(np.abs(colours - median), 0) + 0.01).astype(np.float32)
    # the hole reads as flat ring colour, so its pixels (the object) never reach the tensor
    lum = np.where(hole, float(median @ LUMA), image @ LUMA).astype(np.float32)
    lum = cv2.GaussianBlur(lum, (0, 0), 1.0)
    gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jyy, jxy = (cv2.GaussianBlur(a, (0, 0), cfg.rho) for a in (gx * gx, gy * gy, gx * gy))
    a, b, c = jxx[ring].astype(np.float64), jyy[ring].astype(np.float64), jxy[ring].astype(np.float64)
    trace = a + b
    keep = trace > 1e-12  # a flat pixel has no orientation to vote
    if keep.sum() < 16:
        return RingOrientation((1.0, 0.0), 0.0, median, spread)  # a plain ring: coherence 0
    a, b, c, trace = a[keep], b[keep], c[keep], trace[keep]
    local = np.sqrt((a - b) ** 2 + 4 * c * c) / trace  # local coherence in [0, 1]
    resultant = (local * np.exp(1j * np.arctan2(2 * c, a - b))).sum() / max(local.sum(), 1e-12)
    theta = 0.5 * np.angle(resultant) + np.pi / 2  # the lines run across the mean gradient
    direction = (float(np.cos(theta)), float(np.sin(theta)))
    return RingOrientation(direction, float(abs(resultant)), median, spread)


def known_band(image: np.ndarray, known: np.ndarray, sigma: float) -> np.ndarray:
    """(H, W, 3) the high band of the known pixels: image minus its Gaussian mean over known pixels
    only (normalised convolution), so no hole pixel enters; zero where nothing known is near."""
    k = known.astype(np.float32)
    num = cv2.GaussianBlur(image * k[..., None], (0, 0), sigma)
    den = cv2.GaussianBlur(k, (0, 0), sigma)
    low = num / np.maximum(den, 1e-6)[..., None]
    return np.where((den > 1e-3)[..., None] & known[..., None], image - low, 0.0).astype(np.float32)


def _exit_distance(xs: np.ndarray, ys: np.ndarray, step: tuple[float, float], usable: np.ndarray):
    """For each hole pixel, the distance (px, 0.5 px steps) along `step` to the first usable pixel,
    and whether one was met before the image's edge."""
    H, W = usable.shape
    dist = np.zeros(len(xs), np.float32)
    met = np.zeros(len(xs), bool)
    todo = np.arange(len(xs))
    t = 0.0
    while len(todo) and t < H + W:
        t += 0.5
        px, py = xs[todo] + t * step[0], ys[todo] + t * step[1]
        inside = (px >= 0) & (px <= W - 1) & (py >= 0) & (py <= H - 1)
        todo, px, py = todo[inside], px[inside], py[inside]
        hit = usable[np.round(py).astype(np.int64), np.round(px).astype(np.int64)]
        dist[todo[hit]], met[todo[hit]] = t, True
        todo = todo[~hit]
    return dist, met


def directional_band(
    image: np.ndarray, hole: np.ndarray, cfg: DirectionalConfig | None = None
) -> tuple[np.ndarray, np.ndarray, list[RingOrientation | None]]:
    """The grain band to add to a smooth fill of `hole` (module docstring).

    Args:
        image: (H, W, 3) float [0, 1], finite (NaN / Inf anywhere: ValueError); its hole pixels
            are never read.
        hole: (H, W) bool, True = to fill.
    Returns:
        band (H, W, 3) float32, zero outside the hole and in every connected part of it whose ring is
        not oriented (coherence below `min_coherence`); oriented (H, W) bool, the hole's pixels in
        oriented parts; the orientation of each part (8-connected, in `cv2.connectedComponents`
        order; None where its ring has too few known pixels).
    """
    cfg = cfg or DirectionalConfig()
    image, hole = check_image_mask(image, hole)
    band = np.zeros_like(image)
    oriented = np.zeros_like(hole)
    dist = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 5)
    known = dist >= cfg.guard_px
    if not known.any() or not hole.any():
        return band, oriented, []
    source = known_band(image, known, cfg.sigma)
    H, W = hole.shape
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    orients: list[RingOrientation | None] = []
    for part in range(1, n):
        component = labels == part
        orient = ring_orientation(image, hole, component, cfg)
        orients.append(orient)
        if orient is None or orient.coherence < cfg.min_coherence:
            continue
        oriented |= component
        ys, xs = np.nonzero(component)
        xs, ys = xs.astype(np.float32), ys.astype(np.float32)
        sides = []
        for sign in (1.0, -1.0):
            step = (sign * orient.direction[0], sign * orient.direction[1])
            t, met = _exit_distance(xs, ys, step, known)
            acc = np.zeros((len(xs), 3), np.float32)
            col = np.zeros((len(xs), 3), np.float32)
            cnt = np.zeros(len(xs), np.float32)
            for k in range(cfg.samples):
                qx, qy = xs + (t + k) * step[0], ys + (t + k) * step[1]
                ok = met & (qx >= 0) & (qx <= W - 1) & (qy >= 0) & (qy <= H - 1)
                qxi = np.clip(np.round(qx), 0, W - 1).astype(np.int64)
                qyi = np.clip(np.round(qy), 0, H - 1).astype(np.int64)
                ok &= known[qyi, qxi]
                acc[ok] += source[qyi[ok], qxi[ok]]
                col[ok] += image[qyi[ok], qxi[ok]]
                cnt[ok] += 1
            n_ok = np.maximum(cnt, 1)[:, None]
            sides.append((acc / n_ok, col / n_ok, t, cnt > 0))
        (b1, c1, t1, ok1), (b2, c2, t2, ok2) = sides
        both = ok1 & ok2
        two_surfaces = both & ((np.abs(c1 - c2) / orient.spread).max(-1) > cfg.mismatch)
        off1 = (np.abs(c1 - orient.median) / orient.spread).max(-1)
        off2 = (np.abs(c2 - orient.median) / orient.spread).max(-1)
        ok1 = ok1 & ~(two_surfaces & (off1 > off2))  # keep the end nearer the ring's colour
        ok2 = ok2 & ~(two_surfaces & (off2 >= off1))
        both = ok1 & ok2
        total = np.maximum(t1 + t2, 1e-6)
        w1 = np.where(both, t2 / total, ok1.astype(np.float32))  # the nearer side weighs more
        w2 = np.where(both, t1 / total, ok2.astype(np.float32))
        band[ys.astype(np.int64), xs.astype(np.int64)] = b1 * w1[:, None] + b2 * w2[:, None]
    return band, oriented, orients
