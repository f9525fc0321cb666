"""Insertion from ONE edited photo: the object's geometry from the reference alone, and the regions
it covers in every other view, derived here (`InsertConfig.regions = "derive"`), so that the scene
needs no mask for it in any other view. No weights are used.

1. The edit region E_k: where the edited photo differs from the capture (any channel by more than
   `InsertConfig.edit_tol`; inside the reference's mask when the scene has one), cleaned: connected
   components under `min_component` of the largest are dropped, holes are filled (an object with
   a see-through hole loses it).
2. The supporting surface: the object rests on the surface under its footprint. The scene's sparse
   points that project into a band around E_k's bottom edge (widened up to four times when too few
   fall there) are fitted with a plane by RANSAC (`fit_surface`); hypotheses whose normal is more
   than 60 degrees from the reference camera's up direction are refused first (objects rest on
   floors and tables, and photos are taken roughly upright).
3. Placement: each silhouette column's lowest pixel in the bottom band of E_k is a contact; its ray
   meets the surface at C_x. A contact more than `RECEDE_MAX` of the contacts' sideways spread
   behind their median is the flank of an object wider above its foot (a cup, a vase), not a
   contact: it is dropped (on the cup capture such flanks pushed its sides back by 1.7 cup radii).
   The object's front is vertical (perpendicular to the surface) and faces the camera: the plane
   of normal b (the horizontal direction toward the camera) through C_x, per column
   (`contact = "columns"`: a prism over the contact curve; columns that do not reach the bottom
   band are interpolated) or one plane through the contacts' median (`contact = "plane"`: a
   billboard). Each edited pixel is placed where its ray meets its front.
4. Thickness: `profile = "revolve"` (default) makes the object a solid of revolution about the
   vertical behind its foot (`coin_cl.pipeline.insert_revolve`: the silhouette's outline gives the
   radius at each height, the back is the front's mirror image). Otherwise from the front the
   object extends away from the camera by D = `thickness` x its width along the surface
   (`profile = "extrude"`, a prism), or by D scaled by the silhouette's distance transform
   (`profile = "rounded"`, thinner toward the outline). Each ray is sampled from its front to the
   back at about a pixel's spacing; samples under the surface are dropped. Every sample carries its
   ray's edited colour: faces the reference never saw (sides, back) take the colour of the nearest
   lifted pixel on the same ray.
5. Regions: the lifted points projected into view n, one-pixel cracks closed and holes filled
   (the object's footprint there, F_n), grown by `region_margin` px (R_n, the region of every later
   stage; the margin holds captured background and lets Ref-GS / TE-D blend the edge).

Measured on the synthetic insertion room (the red box on the table, 12 views at 96x72 on a
180-degree arc, the box's true appearance pasted into the view that shows it largest; the initial
images of stage 1 against the truth; `tests/test_pipeline_insert_geometry.py`):

    variant (thickness 0.65)   33 deg: depth rel. / colour reach   98-115 deg: recall   area / truth
    revolve                    3.1 % / 0.93                        1.00                 <= 1.86
    columns + extrude          0.9 % / 0.98                        1.00                 <= 1.94
    columns + rounded          0.8 % / 0.98                        0.76 (a thin shell from the side)
    plane + extrude            2.2 % / 0.87                        0.85-0.94 (a corner-on box's front
                                                                   corner lands behind its place)

A box is the prism's best case, and the solid of revolution still holds its place and outline
(depth within 3.5 % in every view of the arc, recall 1.00); on a round object the prism fails
(`tests/test_pipeline_insert_revolve.py`: a cone seen from the side, behind and above, recall
0.75-0.93 against >= 0.95 for revolve; on the cup capture it is a slab from the side and from
above, docs/RUN.md "Insertion on a real capture"), so "revolve" is the default. For the prism,
thickness 0.65 keeps every derived region under twice the box's true area (0.8: up to 2.4x) with a
recall of at least 0.97, and the flat top (a column's top pixel sees the object's top at its back)
brings the box's top from 0.10 above its true height to 0.04. Trustworthy within about 60 degrees
of the edited view around the surface normal, at about its elevation; to about 120 degrees the
place and outline still hold but the sides are guessed; beyond, the back is the front's mirror.
The box is red on all four sides, which flatters the guessed colours.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import cv2
import numpy as np

from coin_cl.pipeline.insert_revolve import revolve

if TYPE_CHECKING:
    from coin_cl.pipeline.insert_config import InsertConfig
    from coin_cl.scene import Camera, Scene

log = logging.getLogger(__name__)

# Fewest sparse points a surface is fitted to (a plane needs 3; a few more make RANSAC meaningful).
MIN_SURFACE_POINTS = 8
# The band around E_k's bottom edge where the surface's points are taken, as a share of E_k's
# bounding box (half-width sideways and up/down); widened by 2x twice when too few points fall in.
SURFACE_BAND = 0.35
# A column's lowest edited pixel is a contact when it lies in this share of E_k's height from the
# bottom (a handle or an overhang above it is not on the surface).
CONTACT_BAND = 0.25
# A contact lying farther behind the median contact than this share of the contacts' sideways
# spread is not on the surface (lift_one_photo): a disc's rim recedes by about half its width at
# most. Measured: the synthetic box's farthest true contact 0.51 (kept: its depth error at 33
# degrees rose from 0.9 % to 1.0 % when it was dropped at 0.5), the cup capture's flanks 0.59, 0.66.
RECEDE_MAX = 0.55
# Largest angle between a fitted surface's normal and the reference camera's up direction.
MAX_TILT_DEG = 60.0
RANSAC_ITERS = 256
# Spacing of the samples along a ray, in pixels of the reference at that depth.
SAMPLE_PX = 0.7
# The derived regions' default margin, as a share of the view's longer side.
REGION_MARGIN_SHARE = 0.01
# Occlusion of the object by the scene (`occluded`): a sparse point more than this share of the
# object's width above the supporting surface may hide it (the surface's own points lie in front of
# the object's foot in most views and do not); it hides the pixels within this share of the view's
# longer side around it (at least 2 px; the sparse cloud leaves gaps between its points, which the
# same disc closes), where it is nearer than the object by more than OCCLUDER_TOL of its depth.
OCCLUDER_ABOVE = 0.05
OCCLUDER_RADIUS_SHARE = 0.012
OCCLUDER_TOL = 0.03
# A visible part of an occluded object (`visible_footprint`) must show this many pixels of the
# object's outline per pixel of its own width: on the cup capture's insertion the parts beside the
# real cup showed 1.4-2.8, a gap in its points on a plain patch of its print 0.3 (at a corner).
OUTLINE_TOUCH = 0.5


class OnePhotoLift(NamedTuple):
    """The object lifted from one photo: points [M, 3] float32 world, colors [M, 3] float32,
    region [H, W] bool (E_k), depth [H, W] float32 (camera z of the object's front in the
    reference on E_k, NaN elsewhere), plane (4,) float64 (n, d with n . x = d, n unit, toward the
    camera), width (float, scene units), thickness (D, scene units)."""

    points: np.ndarray
    colors: np.ndarray
    region: np.ndarray
    depth: np.ndarray
    plane: np.ndarray
    width: float
    thickness: float


def clean_region(raw: np.ndarray, min_component: float) -> np.ndarray:
    """`raw` (H, W) bool without connected components (8-connected) smaller than `min_component`
    times the largest, and with its holes filled (H, W) bool."""
    raw = np.asarray(raw, bool)
    if not raw.any():
        return raw.copy()
    n, lab, stats, _ = cv2.connectedComponentsWithStats(raw.astype(np.uint8), connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = np.zeros(n, bool)
    keep[1:] = area >= min_component * area.max()
    out = keep[lab]
    # holes: background not connected to the image border (flood fill from a padded corner)
    pad = np.pad(out.astype(np.uint8), 1)
    ff = pad.copy()
    cv2.floodFill(ff, None, (0, 0), 1)
    holes = (ff == 0)[1:-1, 1:-1]
    return out | holes


def edit_region_free(edited: np.ndarray, captured: np.ndarray, mask: np.ndarray | None,
                     cfg: InsertConfig) -> np.ndarray:  # fmt: skip
    """E_k (module doc, step 1): (H, W) bool; inside `mask` when it has any pixel."""
    raw = np.abs(np.asarray(edited) - np.asarray(captured)).max(-1) > cfg.edit_tol
    if mask is not None and np.asarray(mask).any():
        raw &= np.asarray(mask, bool)
    return clean_region(raw, cfg.min_component)


def _up(cam: Camera) -> np.ndarray:
    """The camera's up direction in world coordinates (image y points down)."""
    return -cam.camtoworld[:3, 1]


def fit_surface(cam: Camera, region: np.ndarray, points: np.ndarray, source: str, seed: int = 0,
                tol: float = 0.01) -> np.ndarray:  # fmt: skip
    """The plane (n, d) (4,) float64 the object rests on (module doc, step 2): n . x = d, n unit and
    toward `cam`. `points` [N, 3] world; `tol`: inlier distance as a share of the band points'
    median camera z. Raises ValueError naming `source` when fewer than MIN_SURFACE_POINTS points
    fall around the edit's bottom edge."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    uv, z = cam.project(pts)
    vis = cam.in_image(uv) & (z > 0)
    ys, xs = np.nonzero(region)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    w, h = x1 - x0, y1 - y0
    sel = np.zeros(len(pts), bool)
    for grow in (1, 2, 4):
        bx, by = SURFACE_BAND * grow * w, SURFACE_BAND * grow * h
        with np.errstate(invalid="ignore"):
            sel = vis & (uv[:, 0] >= x0 - bx) & (uv[:, 0] <= x1 + bx) & (np.abs(uv[:, 1] - y1) <= by)
        if sel.sum() >= MIN_SURFACE_POINTS:
            break
    if sel.sum() < MIN_SURFACE_POINTS:
        raise ValueError(
            f"{source}: the edit's footprint has no surface under it ({int(sel.sum())} sparse points of "
            f"the scene around its bottom edge in view {cam.name}, {MIN_SURFACE_POINTS} needed): paint the "
            "object standing on a surface the scene's points cover, or give masks of it in every view "
            "(the hull path)"
        )
    P = pts[sel]
    thr = tol * float(np.median(z[sel]))
    rng = np.random.default_rng(seed)
    up, c = _up(cam), cam.center
    cos_max = np.cos(np.radians(MAX_TILT_DEG))
    best: tuple[int, np.ndarray] | None = None
    best_any: tuple[int, np.ndarray] | None = None
    for _ in range(RANSAC_ITERS):
        a, b, e = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, e - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        if n @ (c - a) < 0:
            n = -n
        cnt = int((np.abs(P @ n - n @ a) < thr).sum())
        if best_any is None or cnt > best_any[0]:
            best_any = (cnt, np.append(n, n @ a))
        if n @ up >= cos_max and (best is None or cnt > best[0]):
            best = (cnt, np.append(n, n @ a))
    if best is None:
        if best_any is None:
            raise ValueError(f"{source}: the sparse points around the edit's bottom edge are collinear: "
                             "paint the object standing on a surface the scene's points cover")  # fmt: skip
        log.warning("insert: no surface within %.0f degrees of view %s's up direction under the edit; "
                    "using the plane most points fit", MAX_TILT_DEG, cam.name)  # fmt: skip
        best = best_any
    plane = best[1]
    inl = P[np.abs(P @ plane[:3] - plane[3]) < thr]
    if len(inl) >= 3:  # least-squares refit on the inliers, kept toward the camera
        m = inl.mean(0)
        n = np.linalg.svd(inl - m, full_matrices=False)[2][-1]
        n = n if n @ (c - m) > 0 else -n
        plane = np.append(n, n @ m)
    return plane


def lift_one_photo(edited: np.ndarray, region: np.ndarray, cam: Camera, points: np.ndarray, source: str,
                   cfg: InsertConfig, seed: int = 0) -> OnePhotoLift:  # fmt: skip
    """Steps 2-4 of the module doc for the reference camera `cam`: E_k `region` (H, W) bool of the
    `edited` (H, W, 3) image lifted onto the surface fitted to the scene's sparse `points` [N, 3].
    Raises ValueError naming `source` when the region is empty or has no surface under it."""
    region = np.asarray(region, bool)
    if not region.any():
        raise ValueError(
            f"{source}: the edit paints nothing (no pixel differs from the captured view {cam.name} by "
            f"more than {cfg.edit_tol:.4f}): paint the object into the photo"
        )
    plane = fit_surface(cam, region, points, source, seed, cfg.surface_tol)
    n, d = plane[:3], plane[3]
    c = cam.center
    ys, xs = np.nonzero(region)
    y0, y1 = ys.min(), ys.max() + 1
    if y1 >= region.shape[0]:
        log.warning(
            "insert: the edit in view %s reaches the bottom of the image: its contact with the surface "
            "may lie below the frame, and the object then stands too near",
            cam.name,
        )
    cols = np.unique(xs)
    bottom = np.array([ys[xs == x].max() for x in cols])
    # a contact: the lowest edited pixel of a column near the bottom of E_k; its lower edge meets the surface
    dirs = cam.rays(cols + 0.5, bottom + 1.0)
    den = dirs @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (d - c @ n) / den
    contact = (bottom + 1 >= y1 - CONTACT_BAND * (y1 - y0)) & np.isfinite(t) & (t > 0)
    if not contact.any():
        raise ValueError(
            f"{source}: the bottom edge of the edit in view {cam.name} does not meet the surface fitted "
            "under it (it lies above the horizon): paint the object standing on a surface seen from above"
        )
    C = c + t[contact, None] * dirs[contact]
    v = c - C.mean(0)
    b = v - (v @ n) * n
    if np.linalg.norm(b) < 1e-6 * np.linalg.norm(v):
        raise ValueError(f"{source}: view {cam.name} looks straight down on the surface under the edit: "
                         "edit a view that sees the object from the side")  # fmt: skip
    b /= np.linalg.norm(b)
    s_c = C @ b  # each contact's offset toward the camera
    # A round foot's rim recedes from its median contact by at most half the contacts' spread; a
    # contact farther behind is the side of an object wider above its foot (a cup, a vase), whose
    # lowest pixel in the band does not touch the surface: its column is interpolated instead.
    spread = float(np.ptp(C @ np.cross(n, b)))
    foot = s_c >= np.median(s_c) - RECEDE_MAX * spread
    if not foot.all():
        log.info("insert: %d of %d contacts lie more than %.2f of the foot's width behind the others; "
                 "their columns are interpolated", int((~foot).sum()), len(foot), RECEDE_MAX)  # fmt: skip
        contact[np.flatnonzero(contact)[~foot]] = False
        C, s_c = C[foot], s_c[foot]
    if cfg.profile == "revolve":
        solid = revolve(edited, region, cam, plane, b, C, cfg.max_points)
        z = splat_depth(solid.points, cam)
        depth = np.where(region & np.isfinite(z), z, np.nan).astype(np.float32)
        return OnePhotoLift(solid.points, solid.colors, region, depth, plane, solid.width, solid.thickness)
    if cfg.contact == "plane":
        s_col = np.full(len(cols), float(np.median(s_c)))
    else:
        s_col = np.interp(cols, cols[contact], s_c)
    s = s_col[np.searchsorted(cols, xs)]
    rd = cam.rays(xs + 0.5, ys + 0.5)
    bd = rd @ b
    with np.errstate(divide="ignore", invalid="ignore"):
        z_front = (s - c @ b) / bd
    ok = np.isfinite(z_front) & (z_front > 0) & (bd < 0)
    if not ok.any():
        raise ValueError(f"{source}: no edited pixel of view {cam.name} meets the object's front plane")
    xs, ys, rd, s, z_front = xs[ok], ys[ok], rd[ok], s[ok], z_front[ok]
    front = c + z_front[:, None] * rd
    side = np.cross(n, b)
    width = float(np.ptp(front @ side))
    D_max = cfg.thickness * width
    if cfg.profile == "rounded":
        dt = cv2.distanceTransform(region.astype(np.uint8), cv2.DIST_L2, 3)[ys, xs]
        D = D_max * dt / max(float(dt.max()), 1e-6)
    else:
        D = np.full(len(xs), D_max)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_back = (s - D - c @ b) / bd[ok]
    z_back = np.maximum(np.where(np.isfinite(z_back), z_back, z_front), z_front)
    f = float(cam.K[0, 0])
    step = SAMPLE_PX * z_front / f
    n_s = np.ceil((z_back - z_front) / step).astype(np.int64) + 1
    total = int(n_s.sum())
    if total > cfg.max_points:  # coarser steps rather than more memory
        n_s = np.maximum(1, (n_s * cfg.max_points / total).astype(np.int64))
    idx = np.repeat(np.arange(len(xs)), n_s)
    k = np.arange(len(idx)) - np.repeat(np.cumsum(n_s) - n_s, n_s)
    frac = k / np.maximum(n_s[idx] - 1, 1)
    zz = z_front[idx] + frac * (z_back - z_front)[idx]
    P = c + zz[:, None] * rd[idx]
    height = P @ n - d
    eps = 1e-3 * float(np.median(z_front))
    # flat top: a column's top pixel sees the object's top at its back (a box's top face, a cup's
    # far rim), so nothing in that column rises above where that ray meets the back
    col = np.searchsorted(cols, xs)
    top_y = np.full(len(cols), np.inf)
    np.minimum.at(top_y, col, ys.astype(np.float64))
    is_top = ys == top_y[col]
    h_top = np.full(len(cols), np.inf)
    np.minimum.at(h_top, col[is_top], (c + z_back[is_top, None] * rd[is_top]) @ n - d)
    keep = (height >= -eps) & (height <= h_top[col[idx]] + eps)
    P, idx, zz = P[keep], idx[keep], zz[keep]
    depth = np.full(region.shape, np.nan, np.float32)
    first = np.full(len(xs), np.inf)
    np.minimum.at(first, idx, zz)
    seen = np.isfinite(first)
    depth[ys[seen], xs[seen]] = first[seen]
    log.info("insert: surface n=(%.2f, %.2f, %.2f) under the edit; %d contacts, width %.3f, thickness %.3f "
             "(%s, %s); %d lifted points", *n, int(contact.sum()), width, D_max, cfg.contact, cfg.profile,
             len(P))  # fmt: skip
    return OnePhotoLift(P.astype(np.float32), np.asarray(edited)[ys[idx], xs[idx]].astype(np.float32),
                        region, depth, plane, width, float(D_max))  # fmt: skip


def splat_depth(points: np.ndarray, cam: Camera) -> np.ndarray:
    """Z-buffer of `points` [M, 3] in `cam`: (H, W) float32 camera z of the nearest point per pixel,
    inf where none lands."""
    px, ok = cam.pixels(points)
    _, z = cam.project(points)
    out = np.full((cam.height, cam.width), np.inf)
    np.minimum.at(out, (px[ok, 1], px[ok, 0]), z[ok])
    return out.astype(np.float32)


def splat_colors(points: np.ndarray, colors: np.ndarray, cam: Camera, radius: int = 1
                 ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The colour of the nearest of `points` [M, 3] (`colors` [M, 3]) in each pixel of `cam`, each
    point covering the (2 `radius` + 1)^2 pixels around its own (a surface sampled about a pixel
    apart then hides what lies behind it instead of showing it through its gaps): ((H, W, 3)
    float32, (H, W) float32 weight, 1 where a point lands, else 0)."""
    px, ok = cam.pixels(points)
    _, z = cam.project(points)
    px, z, col = px[ok], z[ok], np.asarray(colors, np.float32)[ok]
    offsets = np.arange(-radius, radius + 1)
    lin_all, z_all, idx_all = [], [], []
    for dy in offsets:
        for dx in offsets:
            x, y = px[:, 0] + dx, px[:, 1] + dy
            inside = (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
            lin_all.append((y * cam.width + x)[inside])
            z_all.append(z[inside])
            idx_all.append(np.flatnonzero(inside))
    lin, zz, idx = np.concatenate(lin_all), np.concatenate(z_all), np.concatenate(idx_all)
    order = np.lexsort((zz, lin))  # by pixel, nearest first
    lin, first = np.unique(lin[order], return_index=True)
    img = np.zeros((cam.height * cam.width, 3), np.float32)
    wt = np.zeros(cam.height * cam.width, np.float32)
    img[lin] = col[idx[order][first]]
    wt[lin] = 1.0
    return img.reshape(cam.height, cam.width, 3), wt.reshape(cam.height, cam.width)


def footprint(points: np.ndarray, cam: Camera) -> np.ndarray:
    """F_n: where `points` [M, 3] land in `cam`, one-pixel cracks closed and holes filled. (H, W) bool."""
    hit = np.isfinite(splat_depth(points, cam))
    if not hit.any():
        return hit
    closed = cv2.morphologyEx(hit.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    return clean_region(closed, 0.0)


def occluded(lift: OnePhotoLift, scene_points: np.ndarray, cam: Camera) -> np.ndarray:
    """Pixels of view `cam` where the scene hides the lifted object: a sparse scene point standing
    above the supporting surface (OCCLUDER_ABOVE) lies nearer than the object there (OCCLUDER_TOL),
    each point covering a disc of OCCLUDER_RADIUS_SHARE of the view. (H, W) bool; all False
    without such points."""
    pts = np.asarray(scene_points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    n, d = lift.plane[:3], float(lift.plane[3])
    above = pts[pts @ n - d > OCCLUDER_ABOVE * lift.width]
    if not len(above):
        return np.zeros((cam.height, cam.width), bool)
    r = max(2, round(OCCLUDER_RADIUS_SHARE * max(cam.width, cam.height)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    scene_z = cv2.erode(splat_depth(above, cam), disc)  # the nearest scene point within r px
    object_z = cv2.erode(splat_depth(lift.points, cam), np.ones((3, 3), np.uint8))  # cracks closed
    with np.errstate(invalid="ignore"):
        hid = np.isfinite(object_z) & (scene_z < (1.0 - OCCLUDER_TOL) * object_z)
    return cv2.morphologyEx(hid.astype(np.uint8), cv2.MORPH_CLOSE, disc).astype(bool)


def visible_footprint(
    lift: OnePhotoLift, scene_points: np.ndarray, cam: Camera, cfg: InsertConfig
) -> np.ndarray:
    """F_n: the object's `footprint` in `cam`, less what the scene hides there (`occluded`, when
    `cfg.occlusion`), without the visible bits that are gaps of the sparse cloud in an occluder,
    not the object peeking out: those under `cfg.min_component` of the whole footprint, and those
    (nearly) enclosed by the occluder, whose stretch of the footprint's outline (or of the image's
    border) is under OUTLINE_TOUCH times their own width (the square root of their area): an object
    seen beside an occluder shows its own edge along it; a plain patch of the occluder with no SfM
    points on it does not, or at a corner. (H, W) bool."""
    foot = footprint(lift.points, cam)
    if not (cfg.occlusion and foot.any()):
        return foot
    seen = foot & ~occluded(lift, scene_points, cam)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(seen.astype(np.uint8), connectivity=8)
    outline = foot & ~cv2.erode(foot.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0).astype(bool)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= cfg.min_component * foot.sum()
    touch = np.bincount(lab[outline], minlength=n)
    keep &= touch >= OUTLINE_TOUCH * np.sqrt(stats[:, cv2.CC_STAT_AREA])
    return keep[lab]


def grow(mask: np.ndarray, margin: int) -> np.ndarray:
    """`mask` (H, W) bool dilated by `margin` px (a disc)."""
    if margin <= 0 or not mask.any():
        return np.asarray(mask, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def derive_regions(points: np.ndarray, cameras: list[Camera], margin: int) -> list[np.ndarray]:
    """R_n for every camera: the footprint of the lifted `points` grown by `margin` px."""
    return [grow(footprint(points, cam), margin) for cam in cameras]


def contact_sheet(images: list[np.ndarray], regions: list[np.ndarray], names: list[str],
                  cols: int = 6) -> np.ndarray:  # fmt: skip
    """One PNG-able (H', W', 3) uint8 grid: each view's image with its region's outline in green and
    its name, for a user to check where the object will appear."""
    from coin_cl.scene.io import to_uint8

    tiles = []
    for img, reg, name in zip(images, regions, names, strict=True):
        t = np.ascontiguousarray(to_uint8(img))
        scale = max(1, 192 // max(t.shape[:2]))
        t = cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        r = cv2.resize(reg.astype(np.uint8), (t.shape[1], t.shape[0]), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(r, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(t, contours, -1, (0, 255, 0), 1)
        cv2.putText(t, name, (2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 0), 1, cv2.LINE_AA)
        tiles.append(t)
    # cells fit the largest tile: a capture may mix portrait and landscape views
    h, w = max(t.shape[0] for t in tiles), max(t.shape[1] for t in tiles)
    rows = -(-len(tiles) // cols)
    sheet = np.full((rows * (h + 2), min(cols, len(tiles)) * (w + 2), 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        y, x = divmod(i, cols)
        sheet[y * (h + 2) : y * (h + 2) + t.shape[0], x * (w + 2) : x * (w + 2) + t.shape[1]] = t
    return sheet


def margin_px(cfg: InsertConfig, cam: Camera) -> int:
    """The regions' margin in px: `cfg.region_margin`, or 1 % of the view's longer side (>= 1)."""
    if cfg.region_margin is not None:
        return int(cfg.region_margin)
    return max(1, round(REGION_MARGIN_SHARE * max(cam.width, cam.height)))


def lift_reference(edited: np.ndarray, scene: Scene, k: int, mask_k: np.ndarray | None, source: str,
                   cfg: InsertConfig, seed: int = 0) -> OnePhotoLift:  # fmt: skip
    """E_k of view k (inside `mask_k` when it has pixels) lifted onto the scene's surface."""
    region = edit_region_free(edited, scene.images[k], mask_k, cfg)
    return lift_one_photo(edited, region, scene.cameras[k], scene.points, source, cfg, seed)


def derive_masks(edited: np.ndarray, scene: Scene, masks: list[np.ndarray], k: int, source: str,
                 cfg: InsertConfig, seed: int = 0) -> list[np.ndarray]:  # fmt: skip
    """The masks of every stage of a one-photo insertion: R_n (module doc, step 5) for every view of
    the scene, E_k grown by the same margin for the edited view k. Per view (H, W) bool."""
    lift = lift_reference(edited, scene, k, masks[k], source, cfg, seed)
    out = []
    for i, cam in enumerate(scene.cameras):
        m = margin_px(cfg, cam)
        out.append(
            grow(lift.region, m) if i == k else grow(visible_footprint(lift, scene.points, cam, cfg), m)
        )
    return out


def run_insert_derived(scene: Scene, masks: list[np.ndarray], train: list[int], k: int, edited: np.ndarray,
                       out_dir: Path, cfg: InsertConfig, source: str, seed: int = 0,
                       device: Any = None) -> dict[str, Any]:  # fmt: skip
    """Stage 1 of a one-photo insertion (module doc): `masks` are the derived regions
    (`derive_masks`). Writes, in `out_dir`: images/<stem>.png (I^_n: the capture with the object
    warped in by the engine's z-buffered point warp; the edited photo for k), footprints/<stem>.png
    (R_n, the masks of every later stage), edit/points.ply (the lift with its colours),
    edit/region.png (E_k), edit/depth.npy (camera z of the object's front in view k, NaN off E_k),
    edit/views.json (per-view areas) and edit/regions.png (a contact sheet of every training view
    with its region outlined). Returns JSON-able figures."""
    from coin_cl.pipeline.reprojection import reference_in_view
    from coin_cl.scene.io import to_uint8, write_npy, write_png, write_text
    from coin_cl.scene.masks import write_mask
    from coin_cl.scene.ply import write_points_ply

    lift = lift_reference(edited, scene, k, masks[k], source, cfg, seed)
    out_dir = Path(out_dir)
    write_points_ply(out_dir / "edit" / "points.ply", lift.points, lift.colors)
    write_mask(out_dir / "edit" / "region.png", lift.region)
    write_npy(out_dir / "edit" / "depth.npy", lift.depth)
    views, images = {}, []
    cam_k = scene.cameras[k]
    for i in train:
        cam, stem = scene.cameras[i], Path(scene.cameras[i].name).stem
        region = np.asarray(masks[i], bool)
        if i == k:
            img, foot = edited, lift.region
        else:
            foot = visible_footprint(lift, scene.points, cam, cfg) & region
            if cfg.profile == "revolve":  # the mirrored back carries its own colours, not the pixel in front
                col, wt = splat_colors(lift.points, lift.colors, cam)
            else:
                col, wt = reference_in_view(edited, cam, cam_k, lift.points, None, device)
            crack = foot & ~(wt > 0)
            if crack.any():  # a pixel the closing added: the colour of its neighbours
                filled = cv2.inpaint(to_uint8(col), crack.astype(np.uint8), 2, cv2.INPAINT_TELEA)
                col = np.where(crack[..., None], filled.astype(np.float32) / 255.0, col)
            img = np.clip(np.where(foot[..., None], col, scene.images[i]), 0, 1).astype(np.float32)
        write_png(out_dir / "images" / f"{stem}.png", to_uint8(img))
        write_mask(out_dir / "footprints" / f"{stem}.png", region)
        views[stem] = {"object_px": int(foot.sum()), "region_px": int(region.sum())}
        images.append(img)
    write_text(out_dir / "edit" / "views.json", json.dumps(views, indent=1, sort_keys=True))
    sheet = contact_sheet(images, [np.asarray(masks[i], bool) for i in train],
                          [Path(scene.cameras[i].name).stem for i in train])  # fmt: skip
    write_png(out_dir / "edit" / "regions.png", sheet)
    n_empty = sum(v["object_px"] == 0 for v in views.values())
    log.info("insertion from one photo: %d edited pixels lifted to %d points; the object lands in %d of "
             "%d training views; regions in %s and outlined in %s", int(lift.region.sum()), len(lift.points),
             len(views) - n_empty, len(views), out_dir / "footprints", out_dir / "edit" / "regions.png",
             )  # fmt: skip
    return {
        "source": "edited reference (stood on the surface under it, warped to the other views)",
        "regions": "derived",
        "reference": cam_k.name,
        "edited_px": int(lift.region.sum()),
        "lifted_points": int(len(lift.points)),
        "surface": [float(v) for v in lift.plane],
        "width": lift.width,
        "thickness": lift.thickness,
        "views_without_object": n_empty,
        "region_over_object": float(
            sum(v["region_px"] for v in views.values()) / max(1, sum(v["object_px"] for v in views.values()))
        ),
    }
