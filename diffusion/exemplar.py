"""The embedded inpainter without weights (paper 4.1's initial inpaint, when no SD2 / dataset inpaint
exists): structure from a smooth solver, texture from exemplar patches of the same scene.

Multi-scale patch-based completion (Wexler et al. 2007, with PatchMatch search, Barnes et al. 2009),
at the hole's own resolution: an image pyramid of a window around the hole is built, the hole at the
coarsest level is started from OpenCV's smooth fill (Telea / FSR), and every level alternates
- search: for each patch overlapping the hole, the nearest patch (sum of squared differences) among the
  patches lying wholly in known pixels of the window, in this view and in the other views given as
  sources (the same window of each; their own masks, grown by a guard ring, excluded), restricted to
  the hole's surroundings (a band of a few hole radii) and to patches whose colour statistics match
  the hole's boundary ring (`ExemplarConfig.source_band`, `source_gate`), by PatchMatch: propagation from
  neighbours at 1, 2, 4 and 8 pixels, random search at halving radii and one global random draw;
- vote: each hole pixel becomes the similarity-weighted mean of the pixels the overlapping patches
  copied (weights exp(-d / 2h^2), h^2 the median patch distance of the level); with the default
  `vote="copy"` it then takes the centre pixel of its own patch's match instead, since the mean of
  several slightly shifted copies blurs the texture they share (the demo room's holes: HF ratio
  0.80 -> 0.83, SWD 179 -> 166, GMSD and m-PSNR unchanged; docs/BENCHMARKS.md).
The nearest-neighbour field is upsampled to the next level. Two outputs (`ExemplarConfig.mode`):
"full" (the synthesis itself) and "hf" (the smooth solver's fill plus the synthesis's high-frequency
band, ``X - G_sigma * X``, times ``hf_gain``): the benchmark `benchmarks/inpaint2d.py` measures both.
The fill is conservative: where the ring around the hole is plain (`ExemplarConfig.plain_rms`) it is
the smooth fill alone; it never takes a colour outside the ring's range (`clamp_tol`); the pixels a
mask covers only partly at the working resolution (a guard ring, `guard_px`) are neither copied nor
used as the smooth fill's boundary, so the object's colours cannot leak into the fill.

Pure numpy + OpenCV, deterministic for a fixed seed (one ``np.random.default_rng(seed)``).
Images (H, W, 3) float [0, 1]; masks (H, W) bool, True = fill.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from .directional import DirectionalConfig, directional_band
from .inpaint2d import check_image_mask, opencv_inpaint

log = logging.getLogger(__name__)

EXEMPLAR_NAME = "embedded exemplar inpainting (smooth structure + the scene's patches)"
STRUCTURES = ("harmonic", "telea", "ns", "fsr_fast", "fsr_best", "fsr_surfaces")  # ExemplarConfig.structure


@dataclass
class ExemplarConfig:
    """patch: patch side in pixels (odd). min_coarse: the hole's longer side at the coarsest pyramid
    level (levels are added until it is reached). em_iters: search+vote rounds per level (the coarsest
    level gets twice as many). pm_iters: PatchMatch iterations per round. context: the working window
    is the hole's bounding box grown by context x its longer side on every side (clipped to the image);
    sources are drawn from it. structure: the smooth solver ('harmonic', 'telea', 'ns', 'fsr_fast',
    'fsr_best', 'fsr_surfaces'; `smooth_fill`). 'fsr_surfaces' (FSR with each surface's colour made
    harmonic) takes FSR's tints out of large holes: on the cup scenes end to end +0.05 to +1.04 dB
    m-PSNR over 'fsr_fast' at two seeds each, the masked VGG distance within 2 % either way; it
    also flattens a multicoloured texture's colour that FSR reconstructs (a periodic pattern's
    structure fill: 39.6 -> 14.4 dB), so it is an option for surfaces of one colour each
    (docs/BENCHMARKS.md, "FSR with each surface's colour made harmonic").
    mode: 'full' or 'hf' (module docstring). hf_sigma: Gaussian sigma (px) splitting the bands in
    'hf' mode. hf_gain: gain of the synthesised high band in 'hf' mode. vote_h: the vote's weight
    bandwidth h^2 in units of the level's median patch distance (smaller: the best patches dominate,
    sharper and noisier). vote: 'mean' (every hole pixel the weighted mean of the overlapping
    patches' pixels) or 'copy' (then each hole pixel takes the pixel its own patch's match has at
    the centre: the mean of several slightly shifted patches blurs the texture they share).
    texture_gain_max: in 'hf' mode the band's gain is raised from hf_gain towards this cap until
    the band inside the hole is as strong (RMS) as the same band in the window's known pixels
    (`texture_gain`; at or below hf_gain: off).
    guard_px: pixels (working resolution) around every view's mask that are never copied from and
    that the fill itself recomputes (only the mask's pixels are written): for masks that leave pixels
    the object covers partly outside them (their mixed colours would be copied, or carried into the
    hole by the smooth fill, as an outline). 0 by default: stage 1's masks are resized conservatively
    (`coin_cl.scene.types.resize_mask`), and a guard also hides the truest pixels of the surroundings
    from the smooth fill (demo room, structure alone: m-PSNR 19.86 -> 18.92 dB with 1 px).
    source_band: source patches are centred at most source_band x the hole's radius (its largest
    inscribed radius, at least the patch side) from the hole, in every view (the same pixels): the
    hole's own surroundings, not the rest of the window. source_gate: source patches must also look
    like the hole's boundary ring: their mean colour within the ring's patches' 1st-99th percentile
    box and their standard deviation at most the ring patches' largest, each widened by gate_tol
    (colour units, [0, 1]); a plain floor is then filled from floor, not from the leaves or shelves
    elsewhere in the window (when fewer than a hole's worth of patches pass, the band alone is used).
    plain_rms: the texture rule. When the RMS of the high band (``x - G_hf_sigma * x``) of the ring's
    known pixels (within a patch side of the hole) is below it, in colour units of [0, 1], the
    surroundings are plain and the fill is the smooth structure fill alone, with no synthesised
    texture: leaving the texture out departs from the ring by less than the threshold, while a
    synthesised one can invent structure, and on a plain surface any smooth fill is closer than a
    collage. 0.012 sits just above a plain surface with
    sensor noise of about 3/255 (0.0096 for Gaussian noise of 0.01) and below every hole of
    benchmarks/inpaint2d.py (0.018-0.114 on SPIn-NeRF's pavement/gravel/leaves, 0.043-0.055 on the
    demo room), so those fills keep their texture (docs/BENCHMARKS.md). 0 turns the rule off.
    clamp_tol: the fill is clipped per channel to the 1st-99th percentile range of the ring's known
    colours widened by this (colour units): the synthesised band's overshoot along an edge (a bright
    halo beside a tile joint) is a colour the surroundings do not have.
    grain: None (default), or in 'hf' mode the grain transport's settings: where a hole's
    surroundings share one dominant orientation, the texture band is theirs carried straight through
    the hole along it (`diffusion.directional`) in place of the synthesis's, over the structure
    fill's low band (below `hf_sigma`); parts of the hole whose ring is not oriented keep the
    synthesis. Measured (docs/BENCHMARKS.md, "Grain transport"): on cup_plain's wood grain closer to
    the photos behind the virtual box (56 training holes, m-PSNR 25.55 -> 26.20 dB, masked VGG
    distance 1.285 -> 1.162), on SPIn-NeRF's holes streaks that are not there (HF ratio 0.89 -> 0.60
    on 16 scene holes), so it is an option for surfaces known to be grained.
    grain_structure: with `grain`, the smooth solver under the grain band (from STRUCTURES; None:
    `structure`)."""

    patch: int = 7
    min_coarse: int = 12
    em_iters: int = 3
    pm_iters: int = 3
    context: float = 1.0
    structure: str = "fsr_fast"
    mode: str = "hf"
    hf_sigma: float = 2.0
    hf_gain: float = 1.05
    vote_h: float = 1.0
    vote: str = "copy"
    texture_gain_max: float = 1.0
    guard_px: int = 0
    source_band: float = 3.0
    source_gate: bool = True
    gate_tol: float = 0.06
    plain_rms: float = 0.012
    clamp_tol: float = 0.02
    grain: DirectionalConfig | None = None
    grain_structure: str | None = None

    def __post_init__(self) -> None:
        if self.patch < 3 or self.patch % 2 == 0:
            raise ValueError(f"ExemplarConfig.patch must be odd and >= 3, got {self.patch}")
        grain_solver = self.grain_structure or self.structure  # None: the structure's own
        for name, value in (("structure", self.structure), ("grain_structure", grain_solver)):
            if value not in STRUCTURES:
                raise ValueError(f"ExemplarConfig.{name} must be one of {', '.join(STRUCTURES)}, "
                                 f"got {value!r}")  # fmt: skip
        if self.mode not in ("full", "hf"):
            raise ValueError(f"ExemplarConfig.mode must be 'full' or 'hf', got {self.mode!r}")
        if self.min_coarse < 2 or self.em_iters < 1 or self.pm_iters < 0 or self.context < 0:
            raise ValueError("ExemplarConfig: min_coarse >= 2, em_iters >= 1, pm_iters >= 0, context >= 0")
        if self.vote not in ("mean", "copy"):
            raise ValueError(f"ExemplarConfig.vote must be 'mean' or 'copy', got {self.vote!r}")
        if not math.isfinite(self.texture_gain_max):
            raise ValueError(f"ExemplarConfig.texture_gain_max must be finite, got {self.texture_gain_max}")
        if (
            self.guard_px < 0
            or not (self.source_band > 0)
            or not (self.gate_tol >= 0 and self.clamp_tol >= 0)
        ):
            raise ValueError("ExemplarConfig: guard_px >= 0, source_band > 0, gate_tol >= 0, clamp_tol >= 0")
        if not (math.isfinite(self.plain_rms) and self.plain_rms >= 0):
            raise ValueError(f"ExemplarConfig.plain_rms must be finite and >= 0, got {self.plain_rms}")


def smooth_fill(image: np.ndarray, hole: np.ndarray, method: str) -> np.ndarray:
    """The hole of `image` (H, W, 3) float [0, 1] under `hole` (H, W) bool filled by a smooth solver,
    the full image returned: "harmonic" solves Laplace's equation inside the hole with the known
    pixels around it as boundary values (`poisson.poisson_blend` with no guidance: the smoothest
    surface through the ring's colours, no structure of its own), "fsr_surfaces" keeps FSR's
    luminance and makes the colour harmonic within each surface FSR continued
    (`surface_chroma.surface_chroma`), the others are OpenCV's (`inpaint2d.opencv_inpaint`: Telea,
    Navier-Stokes, frequency-selective reconstruction)."""
    if method == "harmonic":
        from .poisson import poisson_blend

        return poisson_blend(image, np.zeros_like(image), hole, hole.astype(np.int8))
    if method == "fsr_surfaces":
        from .surface_chroma import surface_chroma

        return surface_chroma(image, hole, opencv_inpaint(image, hole, "fsr_fast"))
    return opencv_inpaint(image, hole, method)


def _window(mask: np.ndarray, context: float, margin: int) -> tuple[slice, slice]:
    ys, xs = np.nonzero(mask)
    side = max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1)
    g = int(math.ceil(context * side)) + margin
    H, W = mask.shape
    return slice(max(ys.min() - g, 0), min(ys.max() + 1 + g, H)), slice(
        max(xs.min() - g, 0), min(xs.max() + 1 + g, W)
    )


def _down(img: np.ndarray, hole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half size: area-averaged image; a low-res pixel is a hole if any of its pixels is."""
    h, w = hole.shape
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    im = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
    hp = np.pad(hole, ((0, 2 * h2 - h), (0, 2 * w2 - w)), mode="edge")
    return im, hp.reshape(h2, 2, w2, 2).any(axis=(1, 3))


class _Level:
    """One pyramid level: N views of the window, padded by the patch radius r, flattened."""

    def __init__(
        self, imgs: np.ndarray, holes: np.ndarray, target_hole: np.ndarray, r: int, allowed: np.ndarray | None
    ):
        self.r = r
        self.n, self.h, self.w = holes.shape
        pad = ((0, 0), (r, r), (r, r))
        self.hp, self.wp = self.h + 2 * r, self.w + 2 * r
        self.S = np.pad(imgs, pad + ((0, 0),), mode="reflect").reshape(-1, 3).astype(np.float32)
        known = np.pad(~holes, pad, constant_values=False)
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        valid = np.stack([cv2.erode(v.astype(np.uint8), k, borderValue=0) > 0 for v in known])
        if allowed is not None and (valid & (gated := np.pad(allowed, pad, constant_values=False))).any():
            valid &= gated
        self.valid = valid.reshape(-1)
        self.valid_idx = np.flatnonzero(self.valid)
        if len(self.valid_idx) == 0:
            raise ValueError("no fully known patch around the hole: grow the window or use a smaller patch")
        th = np.pad(target_hole, r, constant_values=False)
        self.hole_idx = np.flatnonzero(th)  # in view 0's flat range
        act = cv2.dilate(th.astype(np.uint8), k) > 0
        act[:r], act[-r:], act[:, :r], act[:, -r:] = False, False, False, False
        act |= th
        self.act_idx = np.flatnonzero(act)  # patches overlapping the hole
        dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
        self.off = (dy * self.wp + dx).reshape(-1)

    def refresh_pad(self) -> None:
        """Mirror view 0's current pixels into its padding again (in place): a hole at the image border
        reaches the padding, whose stale copies would otherwise pull the fill back to its start."""
        r = self.r
        v0 = self.S[: self.hp * self.wp].reshape(self.hp, self.wp, 3)
        v0[...] = np.pad(v0[r:-r, r:-r].copy(), ((r, r), (r, r), (0, 0)), mode="reflect")

    def yx(self, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, rem = np.divmod(f, self.hp * self.wp)
        y, x = np.divmod(rem, self.wp)
        return n, y, x

    def flat(self, n, y, x) -> np.ndarray:
        return (n * self.hp + y) * self.wp + x


def _patches(L: _Level, centres: np.ndarray) -> np.ndarray:
    """(M, patch^2, 3) the pixels of the patches centred at flat indices `centres` (M,). np.take
    along the pixel axis: the same values as ``L.S[idx]``, about 2.7x faster (the search's cost)."""
    return np.take(L.S, centres[:, None] + L.off[None, :], axis=0)


def _patch_cost(L: _Level, tgt: np.ndarray, src: np.ndarray) -> np.ndarray:
    d = _patches(L, src)
    d -= tgt
    return np.einsum("mkc,mkc->m", d, d)


def _search(L: _Level, nnf: np.ndarray, cost: np.ndarray, tgt: np.ndarray, iters: int, rng) -> None:
    """PatchMatch on the active patches (in place): propagation, random search, one global draw."""
    grid = np.full(L.hp * L.wp, -1, np.int64)
    size = L.S.shape[0]

    def try_cand(cand: np.ndarray, ok: np.ndarray) -> None:
        idx = np.flatnonzero(ok & (cand >= 0) & (cand < size))
        cand = cand[idx]
        keep = L.valid[cand]
        idx, cand = idx[keep], cand[keep]
        if len(idx) == 0:
            return
        # every patch a candidate (the random search's draws): no copy of the targets
        c = _patch_cost(L, tgt if len(idx) == len(tgt) else np.take(tgt, idx, axis=0), cand)
        better = c < cost[idx]
        sel = idx[better]
        nnf[sel], cost[sel] = cand[better], c[better]

    for it in range(iters):
        grid[L.act_idx] = nnf
        sign = 1 if it % 2 == 0 else -1
        for step in (1, 2, 4, 8):
            for d in (sign * step, sign * step * L.wp, -sign * step, -sign * step * L.wp):
                q = L.act_idx - d
                inside = (q >= 0) & (q < len(grid))
                nb = np.where(inside, grid[np.clip(q, 0, len(grid) - 1)], -1)
                try_cand(nb + d, nb >= 0)
        n, y, x = L.yx(nnf)
        R = max(L.h, L.w)
        while R >= 1:
            yy = np.clip(y + rng.integers(-R, R + 1, len(nnf)), 0, L.hp - 1)
            xx = np.clip(x + rng.integers(-R, R + 1, len(nnf)), 0, L.wp - 1)
            try_cand(L.flat(n, yy, xx), np.ones(len(nnf), bool))
            R //= 2
        try_cand(rng.choice(L.valid_idx, len(nnf)), np.ones(len(nnf), bool))


def _vote(L: _Level, nnf: np.ndarray, cost: np.ndarray, vote_h: float = 1.0) -> np.ndarray:
    """New values (K, 3) of the hole pixels: similarity-weighted mean of the overlapping patches' copies."""
    grid = np.full(L.hp * L.wp, -1, np.int64)
    grid[L.act_idx] = nnf
    wgrid = np.zeros(L.hp * L.wp, np.float32)
    h2 = max(vote_h * float(np.median(cost)), 1e-8)
    # exponent capped: a pixel covered only by poor matches must keep a (tiny) weight, not 0/0
    wgrid[L.act_idx] = np.exp(-np.minimum(cost / (2 * h2), 60.0))
    acc = np.zeros((len(L.hole_idx), 3), np.float32)
    wsum = np.zeros(len(L.hole_idx), np.float32)
    for o in L.off:
        p = L.hole_idx - o
        src = grid[p]
        ok = src >= 0
        w = wgrid[p[ok]]
        acc[ok] += w[:, None] * np.take(L.S, src[ok] + o, axis=0)
        wsum[ok] += w
    return acc / np.maximum(wsum, 1e-35)[:, None]


def _copy_centres(L: _Level, nnf: np.ndarray) -> None:
    """The 'copy' vote: each hole pixel takes the centre pixel of its own patch's match (in place);
    a pixel whose patch has no match keeps the mean vote's value."""
    grid = np.full(L.hp * L.wp, -1, np.int64)
    grid[L.act_idx] = nnf
    src = grid[L.hole_idx]
    ok = src >= 0
    L.S[L.hole_idx[ok]] = L.S[src[ok]]


def _upsample_nnf(Lc: _Level, nnf_c: np.ndarray, Lf: _Level, rng) -> np.ndarray:
    gc = np.full(Lc.hp * Lc.wp, -1, np.int64)
    gc[Lc.act_idx] = nnf_c
    r = Lf.r
    _, y, x = Lf.yx(Lf.act_idx)
    yc = np.clip((y - r) // 2 + r, 0, Lc.hp - 1)
    xc = np.clip((x - r) // 2 + r, 0, Lc.wp - 1)
    src = gc[Lc.flat(0, yc, xc)]
    n, sy, sx = Lc.yx(np.maximum(src, 0))
    fy = np.clip(2 * (sy - r) + r + (y - r) % 2, 0, Lf.hp - 1)
    fx = np.clip(2 * (sx - r) + r + (x - r) % 2, 0, Lf.wp - 1)
    out = Lf.flat(n, fy, fx)
    bad = (src < 0) | ~Lf.valid[out]
    out[bad] = rng.choice(Lf.valid_idx, int(bad.sum()))
    return out


def _allowed(imgs: np.ndarray, holes: np.ndarray, cfg: ExemplarConfig, r: int) -> np.ndarray | None:
    """(N, h, w) bool: where source patches may be centred (`ExemplarConfig.source_band`,
    `source_gate`). imgs (N, h, w, 3), holes (N, h, w), view 0's hole the target. None: anywhere."""
    target = holes[0]
    side = 2 * r + 1
    radius = float(cv2.distanceTransform(np.pad(target, 1).astype(np.uint8), cv2.DIST_L2, 3).max())
    dist = cv2.distanceTransform((~target).astype(np.uint8), cv2.DIST_L2, 3)
    band = dist <= cfg.source_band * max(radius, side) + r
    allowed = np.broadcast_to(band, holes.shape).copy()
    if not cfg.source_gate:
        return allowed
    k = np.ones((side, side), np.uint8)
    full = np.stack([cv2.erode((~h).astype(np.uint8), k, borderValue=0) > 0 for h in holes])
    mean = np.stack([cv2.blur(im, (side, side)) for im in imgs])
    var = np.stack([cv2.blur(im * im, (side, side)) for im in imgs]) - mean**2
    std = np.sqrt(np.maximum(var, 0).sum(-1))
    ring = full[0] & (dist <= side + r)
    if ring.sum() < 8:
        return allowed
    lo, hi = np.percentile(mean[0][ring], [1, 99], axis=0)
    smax = std[0][ring].max()
    tol = cfg.gate_tol
    like = ((mean >= lo - tol) & (mean <= hi + tol)).all(-1) & (std <= smax + tol)
    if (allowed & like & full).sum() < target.sum():
        return allowed  # too few ring-like patches to fill the hole from: the band alone
    return allowed & like


def ring_texture(structure: np.ndarray, hole: np.ndarray, cfg: ExemplarConfig) -> float:
    """RMS (colour units of [0, 1]) of the high band ``x - G_hf_sigma * x`` of the known pixels within a
    patch side of the hole: the surroundings' texture level (`ExemplarConfig.plain_rms`). structure
    (h, w, 3): the image with its hole already smoothly filled (so the object's own pixels do not
    enter the blur), hole (h, w) bool. No ring pixel: inf (not plain)."""
    side = cfg.patch
    near = cv2.dilate(hole.astype(np.uint8), np.ones((2 * side + 1, 2 * side + 1), np.uint8)) > 0
    ring = near & ~hole
    if not ring.any():
        return math.inf
    band = structure - cv2.GaussianBlur(structure, (0, 0), cfg.hf_sigma)
    return float(np.sqrt((band[ring] ** 2).sum(-1).mean() / 3))


def ring_range(window: np.ndarray, hole: np.ndarray, cfg: ExemplarConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (lo, hi) (3,) of the colours of the known pixels within a patch side of the hole:
    their 1st and 99th percentiles widened by `cfg.clamp_tol`. The fill is clipped to it."""
    side = cfg.patch
    near = cv2.dilate(hole.astype(np.uint8), np.ones((2 * side + 1, 2 * side + 1), np.uint8)) > 0
    ring = window[near & ~hole]
    if len(ring) == 0:
        return np.zeros(3, np.float32), np.ones(3, np.float32)
    lo, hi = np.percentile(ring, [1, 99], axis=0)
    return (lo - cfg.clamp_tol).astype(np.float32), (hi + cfg.clamp_tol).astype(np.float32)


def _synthesise(
    imgs: np.ndarray, holes: np.ndarray, init: np.ndarray, cfg: ExemplarConfig, rng
) -> np.ndarray:
    """imgs (N, h, w, 3) window crops (view 0 = the target, its hole pixels ignored), holes (N, h, w)
    unknown pixels, init (h, w, 3) the smooth fill of view 0. Returns view 0 completed (h, w, 3)."""
    r = cfg.patch // 2
    ys, xs = np.nonzero(holes[0])
    side = max(np.ptp(ys) + 1, np.ptp(xs) + 1)
    n_levels = 1
    while side / 2**n_levels >= cfg.min_coarse and min(holes.shape[1:]) / 2**n_levels >= 4 * cfg.patch:
        n_levels += 1
    pyr = [(imgs, holes, init)]
    for _ in range(n_levels - 1):
        im, ho, it = pyr[-1]
        dn = [_down(im[i], ho[i]) for i in range(len(im))]
        it2 = cv2.resize(it, (dn[0][0].shape[1], dn[0][0].shape[0]), interpolation=cv2.INTER_AREA)
        pyr.append((np.stack([d[0] for d in dn]), np.stack([d[1] for d in dn]), it2))
    prev = None
    for lev in range(n_levels - 1, -1, -1):
        im, ho, it = pyr[lev]
        if not (~ho[0]).any():
            continue
        im = im.copy()
        im[0][ho[0]] = it[ho[0]]  # never the masked-out object's own pixels
        for i in range(1, len(im)):
            im[i][ho[i]] = 0.5  # nor theirs in the other views (never copied; a neutral value for the pad)
        L = _Level(im, ho, ho[0], r, _allowed(im, ho, cfg, r))
        if prev is None:
            nnf = rng.choice(L.valid_idx, len(L.act_idx))
        else:
            nnf = _upsample_nnf(prev[0], prev[1], L, rng)
            L.S[L.hole_idx] = _vote(L, nnf, np.ones(len(nnf), np.float32))
            if cfg.vote == "copy":
                _copy_centres(L, nnf)
            L.refresh_pad()
        rounds = cfg.em_iters * (2 if prev is None else 1)
        for _ in range(rounds):
            tgt = _patches(L, L.act_idx)
            cost = _patch_cost(L, tgt, nnf)
            _search(L, nnf, cost, tgt, cfg.pm_iters, rng)
            L.S[L.hole_idx] = _vote(L, nnf, cost, cfg.vote_h)
            if cfg.vote == "copy":
                _copy_centres(L, nnf)
            L.refresh_pad()
        prev = (L, nnf)
    out = prev[0].S.reshape(prev[0].n, prev[0].hp, prev[0].wp, 3)[0]
    return out[r:-r, r:-r].copy()


def texture_gain(window: np.ndarray, hole: np.ndarray, hf: np.ndarray, cfg: ExemplarConfig) -> float:
    """The high band's gain in 'hf' mode: `cfg.hf_gain`, raised (at most to `cfg.texture_gain_max`)
    until the band's RMS inside the hole equals the RMS of the same band of the window's known
    pixels (away from the hole by 2 sigma, so the object's edge does not count as texture).
    window (h, w, 3) the image's window, hole (h, w) bool, hf (h, w, 3) the synthesis's band."""
    if cfg.texture_gain_max <= cfg.hf_gain:
        return cfg.hf_gain
    r = max(1, int(round(2 * cfg.hf_sigma)))
    near = cv2.dilate(hole.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0
    known = ~near
    own = window - cv2.GaussianBlur(window, (0, 0), cfg.hf_sigma)
    if known.sum() < 16 or not hole.any():
        return cfg.hf_gain
    rms_known = float(np.sqrt((own[known] ** 2).mean()))
    rms_hole = float(np.sqrt((hf[hole] ** 2).mean()))
    if not (rms_hole > 0 and np.isfinite(rms_known)):
        return cfg.hf_gain
    return float(np.clip(rms_known / rms_hole, cfg.hf_gain, cfg.texture_gain_max))


def exemplar_inpaint(
    image: np.ndarray,
    mask: np.ndarray,
    cfg: ExemplarConfig | None = None,
    seed: int = 0,
    sources: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> np.ndarray:
    """Fill `mask` of `image` (module docstring). image (H, W, 3) float [0, 1], mask (H, W) bool;
    sources: other views of the scene as (image (H, W, 3), unknown (H, W) bool) pairs of the same size,
    whose known pixels in the same window are also copied from. Returns (H, W, 3) float32, pixels
    outside the mask bit-identical. Empty mask: the input; a mask covering everything: ValueError."""
    cfg = cfg or ExemplarConfig()
    image, mask = check_image_mask(image, mask)
    if not mask.any():
        return image.copy()
    if mask.all():
        raise ValueError("mask covers the whole image: no exemplar patches to copy")
    guard = np.ones((2 * cfg.guard_px + 1,) * 2, np.uint8)
    work = cv2.dilate(mask.astype(np.uint8), guard) > 0  # the hole as filled: mask + guard ring
    if work.all():
        raise ValueError("mask (with its guard ring) covers the whole image: no exemplar patches to copy")
    structure = smooth_fill(image, work, cfg.structure)
    win = _window(work, cfg.context, 2 * cfg.patch)
    views = [(image, work)]
    for k, (im, un) in enumerate(sources or []):
        im, un = check_image_mask(im, un)
        if im.shape != image.shape:
            raise ValueError(f"source view {k} is {im.shape}, the image {image.shape}: sources must match")
        views.append((im, cv2.dilate(un.astype(np.uint8), guard) > 0))
    out = image.copy()
    if cfg.plain_rms > 0 and ring_texture(structure[win], work[win], cfg) < cfg.plain_rms:
        out[mask] = np.clip(structure[mask], 0, 1)  # plain surroundings: the smooth fill alone
        return out
    grain, oriented = None, np.zeros_like(work)
    if cfg.mode == "hf" and cfg.grain is not None:
        grain, oriented, orients = directional_band(image, work, replace(cfg.grain, sigma=cfg.hf_sigma))
        log.debug("exemplar: ring coherence %s; grain carried through %d of %d hole pixels",
                  [None if o is None else round(o.coherence, 2) for o in orients],
                  int(oriented.sum()), int(work.sum()))  # fmt: skip
    if oriented.any():  # the grain band replaces the structure's own high band there, not adds to it
        solver = cfg.grain_structure or cfg.structure
        under = structure if solver == cfg.structure else smooth_fill(image, work, solver)
        low = cv2.GaussianBlur(under, (0, 0), cfg.hf_sigma)
        structure = np.where(oriented[..., None], low, structure)
    fill = structure.copy()
    if oriented[work].all():  # every part's surroundings oriented: no synthesis needed
        band = grain[win]
    else:
        imgs = np.stack([v[0][win] for v in views])
        holes = np.stack([v[1][win] for v in views])
        rng = np.random.default_rng(seed)
        try:
            synth = _synthesise(imgs, holes, structure[win], cfg, rng)
        except ValueError as e:
            raise ValueError(f"exemplar inpainting: {e}") from None
        if cfg.mode == "full":
            fill[win] = synth
            band = None
        else:
            band = synth - cv2.GaussianBlur(synth, (0, 0), cfg.hf_sigma)
            if grain is not None:
                band = np.where(oriented[win][..., None], grain[win], band)
    if band is not None:
        fill[win] = structure[win] + texture_gain(image[win], work[win], band, cfg) * band
    lo, hi = ring_range(image[win], work[win], cfg)
    fill = np.clip(fill, lo, hi)  # no colour the surroundings do not have (the band's overshoot)
    out[mask] = np.clip(fill[mask], 0, 1)
    return out
