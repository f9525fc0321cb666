"""Object masks in every view from the object's mask in one (the per-view masks CoIn, paper
section 4, takes as input), without learned weights.

1. The object's depth range: the sparse points seen in the annotated view that fall inside its mask,
   split into depth clusters at relative gaps; the largest cluster's percentiles, padded, bound it.
2. A 3D hull: the annotated mask's pixels back-projected over that depth range (a frustum slice).
3. Each other view: the hull projected and filled is the prior; `segment` (GrabCut by default,
   or a user's model such as SAM) refines it against the image, seeded with the object's sparse
   points that view sees.
4. Consistency: each hull sample is kept when most views that see it put it inside their mask
   (space carving by votes); the kept samples' projection is each view's consensus mask. Views are
   segmented again with the consensus as prior; a view whose mask still disagrees with the consensus
   (IoU below `outlier_iou`) takes the consensus mask and is reported, for the user to check.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from tqdm import tqdm

from ..scene.types import Camera

log = logging.getLogger(__name__)

# segment(image (H, W, 3) float32 in [0, 1], prior (H, W) bool, seeds (N, 2), bg_seeds (M, 2))
# -> (H, W) bool. seeds / bg_seeds: pixel (x, y) of sparse points known to be on the object / off
# it. The hook for a user's segmenter: SAM prompted with the prior's box, the seeds as positive and
# the bg_seeds as negative points fits it. `grabcut_segment` is the default.
Segmenter = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass
class PropagateConfig:
    """Options of `propagate_masks` (defaults work on the SPIn-NeRF scene and the synthetic room).

    depth_percentiles: object depth range from its points' depth percentiles (robust to strays).
    depth_pad: extra depth on both sides of that range, as a fraction of its median depth.
    cluster_gap: a jump in sorted depth larger than this fraction of the median depth splits clusters.
    min_points: fewest object points needed to trust the depth range.
    hull_stride: pixel stride of the annotated mask's pixels that are back-projected.
    hull_depths: depth samples per back-projected pixel.
    margin: the band around the prior where GrabCut may look, as a fraction of the image diagonal.
    grabcut_iters: GrabCut iterations per view.
    vote: fraction of the views seeing a hull sample that must mask it for the sample to stay.
    outlier_iou: a view whose mask has lower IoU with the consensus takes the consensus mask.
    visibility_cell: pixel cell of the z-buffer visibility test used when no tracks are given.
    visibility_tol: a point is visible when within this relative depth of its cell's nearest point.
    """

    depth_percentiles: tuple[float, float] = (5.0, 95.0)
    depth_pad: float = 0.05
    cluster_gap: float = 0.04
    min_points: int = 5
    hull_stride: int = 3
    hull_depths: int = 24
    margin: float = 0.03
    grabcut_iters: int = 4
    vote: float = 0.5
    outlier_iou: float = 0.5
    visibility_cell: int = 8
    visibility_tol: float = 0.03


@dataclass
class PropagateResult:
    """masks: per view (H, W) bool; source: per view "annotation", "segment", "consensus" (an
    outlier replaced by the 3D consensus) or "empty" (the object is not in the view);
    consistency: per view IoU of its mask with the consensus projection (NaN where undefined);
    depth_range: (near, far) of the object in the annotated view; n_object_points."""

    masks: list[np.ndarray]
    source: list[str]
    consistency: list[float]
    depth_range: tuple[float, float]
    n_object_points: int
    object_points: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))


# ------------------------------------------------------------------------------------ geometry


def visible_points(cam: Camera, points: np.ndarray, cfg: PropagateConfig) -> np.ndarray:
    """Indices of `points` (N, 3) visible in `cam` by a coarse z-buffer: in the image and within
    `visibility_tol` of the nearest point falling in the same `visibility_cell` pixel cell."""
    uv, z = cam.project(points)
    ok = np.flatnonzero(cam.in_image(uv) & (z > 0))
    if ok.size == 0:
        return ok
    c = cfg.visibility_cell
    cells = (uv[ok, 1] // c).astype(np.int64) * (cam.width // c + 1) + (uv[ok, 0] // c).astype(np.int64)
    zmin = np.full(cells.max() + 1, np.inf)
    np.minimum.at(zmin, cells, z[ok])
    return ok[z[ok] <= zmin[cells] * (1 + cfg.visibility_tol)]


def depth_range(z: np.ndarray, cfg: PropagateConfig) -> tuple[float, float, np.ndarray]:
    """Depths (N,) of the points in the annotated region -> (near, far, keep (N,) bool): the largest
    depth cluster (ties: the nearest), its percentiles padded by `depth_pad`."""
    order = np.argsort(z)
    zs = z[order]
    med = float(np.median(zs))
    cuts = np.flatnonzero(np.diff(zs) > cfg.cluster_gap * med) + 1
    bounds = np.concatenate([[0], cuts, [len(zs)]])
    sizes = np.diff(bounds)
    k = int(np.argmax(sizes))  # first maximum: the nearest of equally large clusters
    keep = np.zeros(len(z), bool)
    keep[order[bounds[k] : bounds[k + 1]]] = True
    lo, hi = np.percentile(z[keep], cfg.depth_percentiles)
    pad = cfg.depth_pad * float(np.median(z[keep]))
    return float(max(lo - pad, 1e-6)), float(hi + pad), keep


def hull_samples(cam: Camera, mask: np.ndarray, near: float, far: float, cfg: PropagateConfig) -> np.ndarray:
    """The annotated mask back-projected over [near, far]: (K, 3) world points."""
    ys, xs = np.nonzero(mask[:: cfg.hull_stride, :: cfg.hull_stride])
    uv = np.stack([xs * cfg.hull_stride + 0.5, ys * cfg.hull_stride + 0.5], axis=1).astype(np.float64)
    depths = np.linspace(near, far, cfg.hull_depths)
    return np.concatenate([cam.unproject(uv, np.full(len(uv), d)) for d in depths])


def splat(cam: Camera, pts: np.ndarray, radius: float) -> np.ndarray:
    """Points (K, 3) drawn into `cam` as discs of `radius` px, closed and hole-filled: (H, W) bool."""
    uv, z = cam.project(pts)
    ok = cam.in_image(uv) & (z > 0)
    out = np.zeros((cam.height, cam.width), np.uint8)
    if not ok.any():
        return out.astype(bool)
    r = max(1, int(np.ceil(radius)))
    xy = uv[ok].astype(np.int64)
    out[xy[:, 1], xy[:, 0]] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    # discs of radius r around the samples, then a closing that bridges gaps up to the spacing
    out = cv2.morphologyEx(cv2.dilate(out, k), cv2.MORPH_CLOSE, k)
    return fill_holes(out.astype(bool))


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool with enclosed background regions filled."""
    m = np.pad(mask.astype(np.uint8), 1)
    flood = m.copy()
    cv2.floodFill(flood, None, (0, 0), 1)
    return (m | (1 - flood)).astype(bool)[1:-1, 1:-1]


def sample_spacing(cam: Camera, ref: Camera, pts: np.ndarray, n_per_depth: int) -> float:
    """Median pixel distance in `cam` between neighbouring hull samples (the splat radius)."""
    uv, _ = cam.project(pts[: 2 * n_per_depth])
    if len(uv) < 2:
        return 2.0
    d = np.linalg.norm(np.diff(uv[:n_per_depth], axis=0), axis=1)
    dz = (
        np.linalg.norm(uv[n_per_depth : 2 * n_per_depth] - uv[:n_per_depth], axis=1)
        if len(uv) >= 2 * n_per_depth
        else d
    )
    d = np.concatenate([d[np.isfinite(d)], dz[np.isfinite(dz)]])
    return float(np.clip(np.median(d) if d.size else 2.0, 1.0, 0.05 * max(cam.width, cam.height)))


# ------------------------------------------------------------------------------------ segmenting


def grabcut_segment(
    image: np.ndarray,
    prior: np.ndarray,
    seeds: np.ndarray,
    bg_seeds: np.ndarray | None = None,
    margin_px: int = 12,
    iters: int = 4,
    seed_radius: int = 2,
) -> np.ndarray:
    """GrabCut seeded by a prior: probable object inside `prior`, probable background in a band of
    `margin_px` around it, background beyond; object at the `seeds` (N, 2) pixel (x, y) inside the
    prior, background in discs of `seed_radius` at the `bg_seeds` (M, 2). Runs on a crop around the
    prior. (H, W) bool; the prior itself when GrabCut cannot run."""
    H, W = prior.shape
    if not prior.any():
        return prior.copy()
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    band = cv2.dilate(prior.astype(np.uint8), k).astype(bool)
    ys, xs = np.nonzero(band)
    pad = margin_px * 2
    y0, y1 = max(0, ys.min() - pad), min(H, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(W, xs.max() + pad + 1)
    gc = np.full((y1 - y0, x1 - x0), cv2.GC_BGD, np.uint8)
    gc[band[y0:y1, x0:x1]] = cv2.GC_PR_BGD
    gc[prior[y0:y1, x0:x1]] = cv2.GC_PR_FGD
    if bg_seeds is not None:
        for x, y in np.asarray(bg_seeds, np.float64).reshape(-1, 2).astype(np.int64):
            if y0 <= y < y1 and x0 <= x < x1:
                cv2.circle(gc, (int(x - x0), int(y - y0)), seed_radius, int(cv2.GC_BGD), -1)
    for x, y in np.asarray(seeds, np.float64).reshape(-1, 2).astype(np.int64):
        if y0 <= y < y1 and x0 <= x < x1 and prior[y, x]:
            gc[y - y0, x - x0] = cv2.GC_FGD
    if not (gc == cv2.GC_PR_FGD).any() and not (gc == cv2.GC_FGD).any():
        return np.zeros_like(prior)
    if not (gc == cv2.GC_BGD).any():
        # The prior fills the image: GrabCut has no background to learn from.
        return prior.copy()
    crop = np.ascontiguousarray((np.clip(image[y0:y1, x0:x1], 0, 1) * 255).astype(np.uint8))
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(crop, gc, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    except cv2.error as exc:
        log.debug("GrabCut failed (%s); keeping the prior", exc)
        return prior.copy()
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    return keep_largest_components(out, seeds)


def keep_largest_components(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The largest connected component plus any holding a seed (GrabCut leaves specks)."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return fill_holes(mask)
    keep = {1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))}
    H, W = mask.shape
    for x, y in np.asarray(seeds, np.float64).reshape(-1, 2).astype(np.int64):
        if 0 <= y < H and 0 <= x < W and lab[y, x] > 0:
            keep.add(int(lab[y, x]))
    return fill_holes(np.isin(lab, list(keep)))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks; NaN when both are empty."""
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else float("nan")


# ------------------------------------------------------------------------------------ driver


def propagate_masks(
    cameras: Sequence[Camera],
    images: Sequence[np.ndarray],
    ref: int,
    ref_mask: np.ndarray,
    points: np.ndarray,
    seen: Sequence[np.ndarray] | None = None,
    config: PropagateConfig | None = None,
    segment: Segmenter | None = None,
) -> PropagateResult:
    """Masks for every view from the object's mask in view `ref`.

    cameras/images: per view, images (H, W, 3) float32; ref_mask (H, W) bool in view `ref`;
    points (N, 3) sparse points; seen: per view the indices of the points that view observes
    (SfM tracks; None: a z-buffer test on the points). segment: the per-view refiner (`Segmenter`;
    default GrabCut). Raises ValueError when the annotated region holds too few points.
    """
    cfg = config or PropagateConfig()
    ref_mask = np.asarray(ref_mask, bool)
    if not ref_mask.any():
        raise ValueError(f"the annotation of view {cameras[ref].name} is empty; mark the object")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(cameras)
    if seen is None:
        seen = [visible_points(c, points, cfg) for c in cameras]
    cam = cameras[ref]
    idx = np.asarray(seen[ref], np.int64)
    uv, z = cam.project(points[idx])
    inside = cam.in_image(uv) & (z > 0)
    inside[inside] = ref_mask[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
    idx, z = idx[inside], z[inside]
    if len(idx) < cfg.min_points:
        raise ValueError(
            f"only {len(idx)} sparse points fall inside the annotation of view {cam.name} (need "
            f"{cfg.min_points}); annotate a view where the object is large and textured, or use more photos"
        )
    near, far, keep = depth_range(z, cfg)
    obj_idx = idx[keep]
    obj_set = np.zeros(len(points), bool)
    obj_set[obj_idx] = True
    hull = hull_samples(cam, ref_mask, near, far, cfg)
    n_per_depth = len(hull) // cfg.hull_depths
    log.info("object: %d points, depth %.3g..%.3g in view %s, %d hull samples",
             len(obj_idx), near, far, cam.name, len(hull))  # fmt: skip

    # Background for sure: points that project into the annotated view off the (slightly grown)
    # annotation; the whole object projects inside it. (Depth cannot tell: the object's far side,
    # hidden in that view, lies beyond the depth range of its visible points.)
    uvr, zr = cam.project(points)
    okr = cam.in_image(uvr) & (zr > 0)
    grown = cv2.dilate(ref_mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    bg_set = okr.copy()
    bg_set[okr] = ~grown[uvr[okr, 1].astype(int), uvr[okr, 0].astype(int)]

    def seeds_in(v: int, which: np.ndarray, behind: np.ndarray | None = None) -> np.ndarray:
        s = np.asarray(seen[v], np.int64)
        s = s[which[s]]
        uvs, zs = cameras[v].project(points[s])
        ok = cameras[v].in_image(uvs)
        if behind is not None:
            # drop points the object may hide (visibility without tracks is approximate)
            ok[ok] = zs[ok] < behind[uvs[ok, 1].astype(int), uvs[ok, 0].astype(int)]
        return uvs[ok]

    seg = segment
    masks: list[np.ndarray] = [np.zeros((c.height, c.width), bool) for c in cameras]
    masks[ref] = ref_mask.copy()
    radius = [sample_spacing(c, cam, hull, n_per_depth) for c in cameras]

    def hull_depth(v: int) -> np.ndarray:
        """(H, W) nearest hull depth in view v (inf off the hull), spread over the splat radius."""
        c = cameras[v]
        uvh, zh = c.project(hull)
        ok = c.in_image(uvh) & (zh > 0)
        zmap = np.full((c.height, c.width), np.inf, np.float32)
        np.minimum.at(zmap, (uvh[ok, 1].astype(int), uvh[ok, 0].astype(int)), zh[ok].astype(np.float32))
        r = max(1, int(np.ceil(radius[v])))
        return cv2.erode(zmap, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))

    def run(v: int, prior: np.ndarray) -> np.ndarray:
        c = cameras[v]
        if not prior.any():
            return prior
        margin = max(3, int(cfg.margin * np.hypot(c.width, c.height)))
        fg, bg = seeds_in(v, obj_set), seeds_in(v, bg_set, hull_depth(v))
        if seg is not None:
            return np.asarray(seg(images[v], prior, fg, bg), bool)
        return grabcut_segment(images[v], prior, fg, bg, margin, cfg.grabcut_iters)

    others = [v for v in range(n) if v != ref]
    for v in tqdm(others, desc="masks: first pass", unit="view", leave=False):
        masks[v] = run(v, splat(cameras[v], hull, radius[v]))
    # Consensus: hull samples most of the views that see them put inside their masks.
    votes = np.zeros(len(hull))
    count = np.zeros(len(hull))
    for v in range(n):
        uvv, zz = cameras[v].project(hull)
        ok = cameras[v].in_image(uvv) & (zz > 0)
        count[ok] += 1
        votes[ok] += masks[v][uvv[ok, 1].astype(int), uvv[ok, 0].astype(int)]
    carved = hull[votes >= cfg.vote * np.maximum(count, 1)]
    if len(carved) < 0.02 * len(hull):
        log.warning("masks: the views disagree on the object (%d of %d hull samples kept); "
                    "no consistency pass", len(carved), len(hull))  # fmt: skip
        carved = hull
    consensus = [splat(c, carved, r) for c, r in zip(cameras, radius, strict=True)]
    source = ["segment"] * n
    source[ref] = "annotation"
    consistency = [float("nan")] * n
    for v in tqdm(others, desc="masks: consensus pass", unit="view", leave=False):
        if consensus[v].any():
            masks[v] = run(v, consensus[v])
        consistency[v] = iou(masks[v], consensus[v])
        if not consensus[v].any() and not masks[v].any():
            source[v] = "empty"
        elif not consistency[v] >= cfg.outlier_iou:
            log.info("masks: view %s disagrees with the consensus (IoU %.2f); using the consensus",
                     cameras[v].name, consistency[v])  # fmt: skip
            masks[v] = consensus[v]
            source[v] = "consensus"
    consistency[ref] = iou(masks[ref], consensus[ref])
    for v in range(n):
        if masks[v].all():
            raise RuntimeError(f"the mask of view {cameras[v].name} covers the whole image; annotate again")
    return PropagateResult(masks, source, consistency, (near, far), len(obj_idx), points[obj_idx])
