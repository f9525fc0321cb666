"""Planar continuation of the surfaces around a mask (the depth in the masks that CoIn
paper 4.2's depth loss L_D asks for, continued from the surroundings in every view).

D_bg (`coin_cl.gs.background_depth`) fills the cells without a background point by 2D inpainting
(Telea), which blends every depth on the mask's border. Where a mask spans a depth edge (the object
stands on a table in front of a far floor) the blend carries the far side into the near surface's
continuation: on the demo room D_bg lies more than 10 % behind the true object-free surface on 22 %
of the masks' pixels, and the term's front side (full weight) then pushes the true table top back.

Here the surroundings' sparse points (in a ring around the mask) are explained by a few planes
(sequential RANSAC), each split into patches that are connected in the plane (a plane also catches a
band of every surface it crosses: the table's plane cuts the far walls at the table's height), and
each patch supports only the convex hull of its points. A mask pixel's continuation depth is the
nearest patch its ray meets inside the hull, where the pixel also lies between the patch's own
points in the image, along its row or its column (within `BETWEEN_BAND_PX`): a surface is
interpolated across the mask, never extrapolated from one side (on SPIn-NeRF the pavement's plane
would otherwise run on over the gravel beside it).

`background_depth` keeps the nearer of this and the 2D fill: a surface that continues into the mask
can only bring D_bg forward, where the term's weak behind side is what a wrong guess costs.
Measured in the test views' masks (`python benchmarks/carve.py --scene room|spinnerf --dbg-only`):
on the demo room the share more than 10 % behind the truth falls from 26 % to 0.1 %, in front 3.9 %
-> 4.6 %, median error 2.2 % -> 0.8 %. On SPIn-NeRF (against a GS of the object-absent views) the
planes found around the test masks are cut through gravel and a bush, which the slab rule below
refuses, so D_bg stays the 2D fill's there (1.9 % in front, 25 % behind); without that rule they put
10.9 % in front (6.6 % with the in-between rule alone), a ghost the term would let stand.

Planes only: curved or cluttered surroundings (a bush) find no patch and keep the 2D fill.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from coin_cl.scene.masks import dilate_mask

# The ring of surroundings whose points are fitted: this fraction of sqrt(mask area) in pixels.
RING_SCALE = 0.5
RING_MIN_PX = 6
# A point is on a plane within this fraction of the ring points' median camera depth.
PLANE_TOL = 0.01
# A plane patch needs this share of the ring's points, and at least MIN_PATCH_POINTS.
MIN_PATCH_SHARE = 0.05
MIN_PATCH_POINTS = 12
MAX_PLANES = 4
# A plane is a thin slab: of the points within 3 x the tolerance, at least this share lies within
# the tolerance. A plane cut through clutter (gravel and a bush) holds points spread evenly across
# the slab (0.28-0.57 on SPIn-NeRF's test views), a surface holds them near zero (the demo room's
# planes 0.84-0.98, SPIn-NeRF's pavement 0.73-0.76).
MIN_SLAB_SHARE = 0.65
RANSAC_TRIALS = 256
# Points scored per RANSAC hypothesis (a random subset above this; the refit uses all of them).
RANSAC_MAX_POINTS = 4000
# Neighbours closer than this many median nearest-neighbour spacings are one patch ...
LINK_SPACINGS = 3.0
# ... and so are those closer than the mask's size at the ring's depth (a patch bridges the
# footprint the object hides, not the gap to another surface further away).
# A pixel is between a patch's points when they lie on both sides of it within this many rows
# (or columns): the band absorbs the sparsity of SfM points (2 / 4 / 8 px, before the slab rule:
# in-front share on SPIn-NeRF 0.058 / 0.066 / 0.074, behind 0.156 / 0.142 / 0.124; the demo room
# the same at all three).
BETWEEN_BAND_PX = 4


@dataclass
class PlanePatch:
    """A planar patch: `origin` [3] on the plane, unit `normal` [3], in-plane `axes` [2, 3], and
    `hull` (Delaunay of the patch's points in plane coordinates [P, 2]) that bounds its support."""

    origin: np.ndarray
    normal: np.ndarray
    axes: np.ndarray
    hull: Delaunay

    @property
    def points(self) -> np.ndarray:
        """[P, 3] the patch's points, projected onto its plane."""
        return self.origin + self.hull.points @ self.axes

    def contains(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] world points on the plane -> [N] bool, inside the patch's convex hull."""
        q = (np.asarray(points, np.float64) - self.origin) @ self.axes.T
        return self.hull.find_simplex(q) >= 0


def between(cam: Any, points: np.ndarray, rows: np.ndarray, cols: np.ndarray, band: int) -> np.ndarray:
    """[n] bool: pixel (rows[i], cols[i]) of `cam`'s image has some of `points` [P, 3] left and right
    of it within `band` rows, or above and below it within `band` columns."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    H, W = cam.height, cam.width
    px, ok = cam.pixels(points)
    u, v = px[ok, 0], px[ok, 1]
    lo_u, hi_u = np.full(H, W + 1), np.full(H, -1)  # per row: leftmost, rightmost point
    np.minimum.at(lo_u, v, u)
    np.maximum.at(hi_u, v, u)
    lo_v, hi_v = np.full(W, H + 1), np.full(W, -1)  # per column: topmost, lowest point
    np.minimum.at(lo_v, u, v)
    np.maximum.at(hi_v, u, v)
    k = 2 * band + 1
    lo_u, hi_u = minimum_filter1d(lo_u, k, mode="nearest"), maximum_filter1d(hi_u, k, mode="nearest")
    lo_v, hi_v = minimum_filter1d(lo_v, k, mode="nearest"), maximum_filter1d(hi_v, k, mode="nearest")
    return ((lo_u[rows] < cols) & (cols < hi_u[rows])) | ((lo_v[cols] < rows) & (rows < hi_v[cols]))


def _patches(q: np.ndarray, min_points: int, link: float) -> list[np.ndarray]:
    """Index arrays of the connected groups of plane coordinates `q` [N, 2] (neighbours at most
    max(LINK_SPACINGS x median spacing, link) apart) with at least `min_points` points."""
    if len(q) < max(min_points, 3):
        return []
    tree = cKDTree(q)
    spacing = float(np.median(tree.query(q, k=2)[0][:, 1]))
    _, label = connected_components(_link_graph(q, tree, max(LINK_SPACINGS * spacing, link)), directed=False)
    sizes = np.bincount(label)
    return [np.nonzero(label == c)[0] for c in np.nonzero(sizes >= min_points)[0]]


def _link_graph(q: np.ndarray, tree: cKDTree, r: float) -> coo_matrix:
    """A graph on the points `q` [N, 2] with the connected components of "at most `r` apart".

    The Delaunay triangulation's edges of length <= r: the Euclidean minimum spanning tree lies in
    the triangulation, and the components of the r-graph are those of its edges <= r, so this is
    exact with O(N) edges, where listing every pair within r (the link is the mask's size, often
    most of the ring) costs O(N^2): 0.16 s a view on SPIn-NeRF's rings. Points Qhull leaves out of
    the triangulation (duplicates) are linked to their nearest vertex; collinear points (no
    triangulation) take the pair list."""
    n = len(q)
    try:
        tri = Delaunay(q)
    except QhullError:
        pairs = tree.query_pairs(r, output_type="ndarray")
        return coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    s = tri.simplices
    edges = np.concatenate([s[:, [0, 1]], s[:, [1, 2]], s[:, [0, 2]]])
    if len(tri.coplanar):
        edges = np.concatenate([edges, tri.coplanar[:, [0, 2]]])
    edges = edges[np.linalg.norm(q[edges[:, 0]] - q[edges[:, 1]], axis=1) <= r]
    return coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))


def fit_plane_patches(points: np.ndarray, tol: float, min_points: int, link: float = 0.0,
                      seed: int = 0, max_planes: int = MAX_PLANES) -> list[PlanePatch]:  # fmt: skip
    """Planar patches explaining `points` [N, 3] (sequential RANSAC, then connected patches).

    tol: the inlier distance (world units); min_points: the fewest points a plane and a patch keep;
    link: patches closer than this (world units) are joined; seed: RANSAC's generator (the result
    is deterministic for a seed). A plane whose points do not form a thin slab (`MIN_SLAB_SHARE`)
    gives no patch. Degenerate input (fewer than 3 finite points, all collinear) gives none."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    rest = pts[np.isfinite(pts).all(1)]
    rng = np.random.default_rng(seed)
    out: list[PlanePatch] = []
    for _ in range(max_planes):
        if len(rest) < max(min_points, 3):
            break
        score = (
            rest if len(rest) <= RANSAC_MAX_POINTS else rest[rng.choice(len(rest), RANSAC_MAX_POINTS, False)]
        )
        idx = rng.integers(0, len(rest), size=(RANSAC_TRIALS, 3))
        a, b, c = rest[idx[:, 0]], rest[idx[:, 1]], rest[idx[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12 * max(1.0, float(np.abs(rest).max())) ** 2
        if not good.any():
            break
        n, a = n[good] / norm[good, None], a[good]
        dist = np.abs(score @ n.T - np.einsum("tk,tk->t", n, a))  # [S, T]
        best = int(np.argmax((dist < tol).sum(0)))
        inl = np.abs((rest - a[best]) @ n[best]) < tol
        if inl.sum() < min_points:
            break
        # Refit on the inliers (least squares), then take the inliers of the refit.
        q = rest[inl]
        origin = q.mean(0)
        _, _, vt = np.linalg.svd(q - origin, full_matrices=False)
        dist = np.abs((rest - origin) @ vt[2])
        inl = dist < tol
        if inl.sum() < MIN_SLAB_SHARE * (dist < 3 * tol).sum():  # clutter, not a surface: no patch
            rest = rest[~inl]
            continue
        q = rest[inl]
        q2 = (q - origin) @ vt[:2].T
        for group in _patches(q2, min_points, link):
            try:
                hull = Delaunay(q2[group])
            except QhullError:  # collinear: a line supports no surface
                continue
            out.append(PlanePatch(origin, vt[2], vt[:2], hull))
        rest = rest[~inl]
    return out


def patch_depth(cam: Any, region: np.ndarray, patches: list[PlanePatch],
                band: int | None = BETWEEN_BAND_PX) -> np.ndarray:  # fmt: skip
    """[H, W] float64 camera z of the nearest patch each pixel's ray meets inside its hull, for the
    pixels of `region` [H, W] bool that lie `between` the patch's points (band: its row / column
    band; None: no such rule); inf elsewhere and where no patch is met (rays parallel to a plane or
    meeting it behind the camera meet nothing)."""
    H, W = region.shape
    out = np.full((H, W), np.inf)
    if not patches or not region.any():
        return out
    rows, cols = np.nonzero(region)
    uv = np.stack([cols + 0.5, rows + 0.5], axis=1)
    eye = cam.camtoworld[:3, 3]
    ray = cam.unproject(uv, np.ones(len(uv))) - eye  # camera z = 1 along it: t is the depth
    best = np.full(len(uv), np.inf)
    for p in patches:
        den = ray @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p.origin - eye) @ p.normal) / den
        ok = np.isfinite(t) & (t > 0) & (t < best)
        if band is not None:
            ok &= between(cam, p.points, rows, cols, band)
        if not ok.any():
            continue
        hit = np.zeros(len(t), bool)
        hit[ok] = p.contains(eye + ray[ok] * t[ok, None])
        best = np.where(hit, t, best)
    out[rows, cols] = best
    return out


def continuation_depth(cam: Any, mask: np.ndarray, points: np.ndarray, region: np.ndarray | None = None,
                       seed: int = 0) -> np.ndarray:  # fmt: skip
    """[H, W] float64: the planar continuation (module doc) of the background `points` [N, 3] around
    `mask` [H, W] bool into `region` (default: the mask), camera z; inf where no patch reaches."""
    mask = np.asarray(mask, bool)
    region = mask if region is None else np.asarray(region, bool)
    H, W = mask.shape
    area = int(mask.sum())
    if area == 0:
        return np.full((H, W), np.inf)
    px, ok = cam.pixels(points)
    grow = max(RING_MIN_PX, int(RING_SCALE * np.sqrt(area)))
    near = dilate_mask(mask, kernel=2 * grow + 1, iterations=1)  # grown by `grow` px, a square
    sel = ok & near[px[:, 1], px[:, 0]]
    ring = np.asarray(points, np.float64)[sel]
    if len(ring) < MIN_PATCH_POINTS:
        return np.full((H, W), np.inf)
    z = float(np.median(cam.project(ring)[1]))
    link = np.sqrt(area) * z / float(cam.K[0, 0])  # the mask's size, in world units at that depth
    patches = fit_plane_patches(ring, PLANE_TOL * z, max(MIN_PATCH_POINTS, int(MIN_PATCH_SHARE * len(ring))),
                                link, seed)  # fmt: skip
    return patch_depth(cam, region, patches)
