"""The "revolve" profile of a one-photo insertion: the object as a solid of revolution about a
vertical axis (perpendicular to the surface it stands on), for round objects (a cup, a bottle, a
vase, a pot) that the "extrude" prism turns into a slab seen from the side or from above.

The silhouette's outline gives the radius at each height: the leftmost and rightmost edited pixels
of an image row are where the row's rays graze the solid, which for a solid of revolution happens
on the axial plane (through the axis, facing the camera); their half distance there is the radius
at their height. The axis stands on the surface behind the foot's front rim (the contacts) by the
foot's radius. The top is where the topmost pixels' rays meet the far rim (a cup's opening or lid,
seen from above, lies behind the front of its silhouette's top). Only the surface is sampled (side
wall and top disc, about `SAMPLE_PX` apart at the object's depth in the reference): a shell is all
a view's footprint, the warp and Ref-GS's seed need.

Colour by mirror symmetry: a point of the front half (toward the edited camera) takes the colour of
the edited pixel it projects to; a point of the back half takes its mirror image's across the
axial plane (a cup's back looks like its front, not like the pixel in front of it). A point that
projects outside the edit takes the nearest edited pixel's colour.

Measured: `insert_geometry`'s module doc (the synthetic box, whose corners a cylinder cuts) and
docs/RUN.md "Insertion on a real capture" (a cup)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy import ndimage

if TYPE_CHECKING:
    from coin_cl.scene import Camera

log = logging.getLogger(__name__)

# Spacing of the shell's samples, in pixels of the reference at the object's depth (the extrude
# profile's ray spacing, so both profiles seed Ref-GS alike).
SAMPLE_PX = 0.7
# The rows whose widest gives the top's radius: this share of the silhouette's height from its top.
TOP_SHARE = 0.25
# Smallest radius, as a share of the foot's: a pointed top (a bottle's neck, a cone) keeps a ring.
MIN_RADIUS_SHARE = 0.02


class Solid(NamedTuple):
    """A solid of revolution's shell: points [M, 3] float32 world, colors [M, 3] float32, width
    (the largest diameter, scene units), thickness (the foot's diameter along the view)."""

    points: np.ndarray
    colors: np.ndarray
    width: float
    thickness: float


def _hit(c: np.ndarray, rd: np.ndarray, b: np.ndarray, s: float | np.ndarray) -> np.ndarray:
    """Where rays c + t rd (rd [N, 3]) meet the planes x . b = s (t > 0): [N, 3], NaN where they do not."""
    bd = rd @ b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (s - c @ b) / bd
    t = np.where(np.isfinite(t) & (t > 0), t, np.nan)
    return c + t[:, None] * rd


def revolve(
    edited: np.ndarray,
    region: np.ndarray,
    cam: Camera,
    plane: np.ndarray,
    b: np.ndarray,
    contacts: np.ndarray,
    max_points: int,
) -> Solid:
    """The solid of revolution of the module doc. `edited` (H, W, 3), `region` (H, W) bool (E_k),
    `cam` the edited view's camera, `plane` (4,) the surface (n . x = d, n toward the camera), `b`
    (3,) the horizontal unit direction toward the camera, `contacts` [C, 3] the foot's front rim on
    the surface (at least one point). `max_points` caps the shell (coarser spacing beyond it)."""
    n, d = plane[:3], float(plane[3])
    e = np.cross(n, b)
    c = cam.center
    uc, sc = contacts @ e, contacts @ b
    u0 = 0.5 * (uc.max() + uc.min())
    r0 = max(0.5 * float(np.ptp(uc)), 1e-9)
    # the axis behind the rim: each contact at (u, s) lies on the foot's circle of radius r0
    s_a = float(np.median(sc - np.sqrt(np.maximum(r0**2 - (uc - u0) ** 2, 0.0))))

    ys, xs = np.nonzero(region)
    rows = np.unique(ys)
    left = np.array([xs[ys == y].min() for y in rows], np.float64)
    right = np.array([xs[ys == y].max() + 1 for y in rows], np.float64)
    grazing = np.concatenate([cam.rays(left, rows + 0.5), cam.rays(right, rows + 0.5)])
    Q = _hit(c, grazing, b, s_a)
    m = len(rows)
    h_rows = 0.5 * ((Q[:m] @ n) + (Q[m:] @ n)) - d
    r_rows = 0.5 * (Q[m:] @ e - Q[:m] @ e)
    ok = np.isfinite(h_rows) & np.isfinite(r_rows) & (r_rows > 0)
    if not ok.any():
        raise ValueError(f"no row of the edit in view {cam.name} meets the object's axial plane")
    h_rows, r_rows = h_rows[ok], r_rows[ok]
    order = np.argsort(h_rows)
    h_rows, r_rows = h_rows[order], r_rows[order]

    # the top: the topmost pixels see the far rim, whose radius is the widest of the upper rows
    # (the top's outline narrows above its widest row, which lies on the axial plane)
    top_y = ys.min()
    top_x = xs[ys == top_y]
    upper = h_rows >= h_rows[-1] - TOP_SHARE * (h_rows[-1] - h_rows[0])
    r_top = float(r_rows[upper].max())
    far = _hit(c, cam.rays(top_x + 0.5, np.full(len(top_x), top_y + 0.0)), b, s_a - r_top)
    h_top = float(np.nanmedian(far @ n - d)) if np.isfinite(far).all(1).any() else float(h_rows[-1])
    h_top = max(min(h_top, float(h_rows[-1])), 1e-9)

    z_obj = float(np.median(cam.project(contacts)[1]))
    step = SAMPLE_PX * z_obj / float(cam.K[0, 0])
    r_min = MIN_RADIUS_SHARE * r0

    def shell(step: float) -> np.ndarray:
        hs = np.arange(0.0, h_top + 0.5 * step, step)
        rs = np.maximum(np.interp(hs, h_rows, r_rows), r_min)
        # rings of the wall, and between two heights whose radii differ by more than a step, the
        # annulus joining them (a lid's ledge seen from above)
        r_next = np.append(rs[1:], rs[-1])
        pts = []
        for h, r, rn in zip(hs, rs, r_next, strict=True):
            lo, hi = min(r, rn), max(r, rn)
            radii = np.append(np.arange(hi, lo, -step), lo) if hi - lo > step else np.array([r])
            pts.append(_rings(radii, h, step))
        pts.append(_rings(np.arange(rs[-1], 0.0, -step), h_top, step))  # the top disc
        local = np.concatenate(pts)
        return (d * n + u0 * e + s_a * b) + local[:, :1] * e + local[:, 1:2] * b + local[:, 2:3] * n

    P = shell(step)
    while len(P) > max_points:  # coarser spacing rather than more memory: points go with ~1 / step^2
        step *= 1.02 * np.sqrt(len(P) / max_points)
        P = shell(step)

    # colours: the front half as seen, the back half as its mirror across the axial plane
    s = P @ b
    mirrored = P + np.maximum(s_a - s, 0.0)[:, None] * 2.0 * b
    px, _ = cam.pixels(mirrored)
    H, W = region.shape
    ix, iy = np.clip(px[:, 0], 0, W - 1), np.clip(px[:, 1], 0, H - 1)
    _, (ny, nx) = ndimage.distance_transform_edt(~region, return_indices=True)
    colors = np.asarray(edited, np.float32)[ny[iy, ix], nx[iy, ix]]

    width = 2.0 * float(r_rows.max())
    log.info("insert: revolve about an axis %.3f behind the foot's rim, foot radius %.3f, top %.3f above "
             "the surface, widest %.3f; %d shell points", float(np.median(sc)) - s_a, r0, h_top, width,
             len(P))  # fmt: skip
    return Solid(P.astype(np.float32), colors, width, 2.0 * r0)


def _rings(radii: np.ndarray, h: float, step: float) -> np.ndarray:
    """Points (lateral, toward-camera, height) [N, 3] on circles of `radii` at height `h`, about
    `step` apart along each circle."""
    out = []
    for r in radii:
        k = max(3, int(np.ceil(2 * np.pi * r / step)))
        a = np.arange(k) * (2 * np.pi / k)
        out.append(np.stack([r * np.cos(a), r * np.sin(a), np.full(k, h)], 1))
    return np.concatenate(out) if out else np.zeros((0, 3))
