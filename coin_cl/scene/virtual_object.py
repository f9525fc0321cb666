"""A virtual object for a removal benchmark with ground truth: a textured box standing on a surface
of a real capture, its exact footprint in every view, and its flat-shaded appearance.

Geometry only (numpy + OpenCV); `coin_cl.prepare.virtual_scene` turns a capture into a scene with it.

- `VirtualBox`: an oriented box given by the centre of its base, three orthonormal axes (box x,
  box y, up) and its full extents. `box_on_plane` stands one on a plane (`fit_plane`, RANSAC).
- `footprint_mask`: every pixel whose square any ray of the box hits, exactly: the box fully in
  front of the camera projects to the convex hull of its 8 projected corners, and a pixel square
  meets that convex polygon unless a separating axis exists (the polygon's edge normals and the
  image axes; touching along a line does not count). No sampling, so no sliver is missed.
- `render_box`: the box's colour in those pixels, 100% box (never blended with what is behind it):
  `supersample`^2 rays per pixel, averaged over the rays that hit; a mask pixel that only a sliver
  of the box touches (no ray hit) takes the colour of the nearest pixel that has one. The texture
  is procedural (a 4 x 4 grid of cells in a few saturated colours with dark borders per face);
  shading is flat per face: AMBIENT + (1 - AMBIENT) * max(0, n . LIGHT), LIGHT fixed in the box's
  frame (the capture's lighting is unknown; docs/VIRTUAL_OBJECTS.md lists this as a limit).
- `occluders`: the depth test that decides whether the box would be hidden by real geometry in a
  view. The capture's sparse points are the depth proxy: a point whose projection falls in the
  box's footprint and that lies in front of the box's surface along that pixel's ray by more than
  `margin` is real geometry between the camera and the box. A camera on the far side of the
  supporting plane sees the box through the surface (the plane is the second depth proxy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import Camera

# Flat shading: light direction in the box's frame (x, y, up), mostly from above, so the top and two
# sides get three different brightnesses.
LIGHT = np.array([0.45, -0.3, 0.84]) / np.linalg.norm([0.45, -0.3, 0.84])
AMBIENT = 0.45
# Procedural texture: cells per face side, border width (fraction of a cell), palette (RGB in [0, 1]).
TEXTURE_CELLS = 4
TEXTURE_BORDER = 0.08
PALETTE = np.array(
    [
        [0.86, 0.16, 0.12],  # red
        [0.96, 0.78, 0.10],  # yellow
        [0.12, 0.32, 0.82],  # blue
        [0.95, 0.95, 0.93],  # white
        [0.10, 0.58, 0.28],  # green
    ],
    np.float32,
)
BORDER_COLOUR = np.array([0.08, 0.08, 0.10], np.float32)
# A corner closer to the camera than this (camera z, world units) puts the box through the camera.
NEAR = 1e-6


@dataclass
class VirtualBox:
    """An oriented box.

    base: (3,) world position of the centre of its bottom face (on the supporting surface).
    axes: (3, 3) orthonormal, right-handed; columns are the box's x, y and up axes in world space.
    size: (3,) full extents along x, y and up (world units, > 0).
    seed: picks the texture's cell colours.
    """

    base: np.ndarray
    axes: np.ndarray
    size: np.ndarray
    seed: int = 0

    def __post_init__(self) -> None:
        self.base = np.asarray(self.base, np.float64).reshape(3)
        self.axes = np.asarray(self.axes, np.float64).reshape(3, 3)
        self.size = np.asarray(self.size, np.float64).reshape(3)
        if not (np.isfinite(self.size).all() and (self.size > 0).all()):
            raise ValueError(f"box size must be three positive numbers, got {self.size.tolist()}")
        if not np.allclose(self.axes.T @ self.axes, np.eye(3), atol=1e-6) or np.linalg.det(self.axes) < 0:
            raise ValueError("box axes must be orthonormal and right-handed")

    @property
    def center(self) -> np.ndarray:
        """(3,) the box's centre."""
        return self.base + self.axes[:, 2] * self.size[2] / 2

    def corners(self) -> np.ndarray:
        """(8, 3) world corners."""
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return self.center + (s * self.size / 2) @ self.axes.T

    def contains(self, points: np.ndarray, grow: float = 0.0) -> np.ndarray:
        """(N, 3) world points -> (N,) bool: inside the box with every extent grown by `grow` per
        side (negative shrinks; world units). The surface itself counts as inside."""
        local = (np.asarray(points, np.float64).reshape(-1, 3) - self.center) @ self.axes
        return (np.abs(local) <= self.size / 2 + grow).all(axis=1)

    def to_json(self) -> dict:
        """Plain lists: base, axes (columns x, y, up), size, centre, seed."""
        return {"base": self.base.tolist(), "axes": self.axes.tolist(), "size": self.size.tolist(),
                "center": self.center.tolist(), "seed": self.seed}  # fmt: skip


# ---------------------------------------------------------------------------------------- the plane


@dataclass
class Plane:
    """n . x = d with unit normal n (3,); `inliers` = how many points supported it."""

    normal: np.ndarray
    d: float
    inliers: int = 0

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) signed distance along the normal."""
        return np.asarray(points, np.float64).reshape(-1, 3) @ self.normal - self.d

    def project(self, p: np.ndarray) -> np.ndarray:
        """(3,) point -> (3,) its foot on the plane."""
        return np.asarray(p, np.float64) - self.distance(p)[0] * self.normal

    def to_json(self) -> dict:
        return {"normal": self.normal.tolist(), "d": float(self.d), "inliers": int(self.inliers)}


def fit_plane(points: np.ndarray, threshold: float, toward: np.ndarray, seed: int = 0,
              iterations: int = 400) -> Plane:  # fmt: skip
    """RANSAC plane through (N, 3) points (N >= 3): the 3-point plane with the most points within
    `threshold`, refined by least squares (SVD) on its inliers. The normal is oriented towards the
    point `toward` (the cameras: the box stands on the side the capture sees).
    Raises ValueError when fewer than 3 points or all of them collinear."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < 3:
        raise ValueError(f"a supporting plane needs at least 3 sparse points near the box, got {len(pts)}")
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        inl = np.abs((pts - a) @ n) <= threshold
        if inl.sum() > best_n:
            best, best_n = inl, int(inl.sum())
    if best is None or best_n < 3:
        raise ValueError("the sparse points near the box are collinear; no supporting plane can be fitted")
    q = pts[best]
    centroid = q.mean(axis=0)
    n = np.linalg.svd(q - centroid)[2][-1]
    if n @ (np.asarray(toward, np.float64) - centroid) < 0:
        n = -n
    inl = int((np.abs((pts - centroid) @ n) <= threshold).sum())
    return Plane(n, float(n @ centroid), inl)


def box_on_plane(plane: Plane, near: np.ndarray, size, yaw_deg: float = 0.0, seed: int = 0) -> VirtualBox:
    """A box whose base centre is `near` (3,) projected on `plane`, up axis = the plane normal, x axis
    = the world x axis projected on the plane (world y when x is nearly the normal) turned by
    `yaw_deg` about the normal; size (3,) = extents along x, y, up."""
    up = plane.normal
    ref = np.array([1.0, 0.0, 0.0])
    if abs(ref @ up) > 0.9:
        ref = np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ up) * up
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    t = np.radians(yaw_deg)
    x, y = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
    return VirtualBox(plane.project(near), np.stack([x, y, up], axis=1), np.asarray(size, np.float64), seed)


# ----------------------------------------------------------------------------------- the footprint


def _hull(p: np.ndarray) -> np.ndarray:
    """(N, 2) -> convex hull vertices (M, 2), counter-clockwise (monotone chain, float64)."""
    pts = sorted(map(tuple, np.asarray(p, np.float64)))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for q in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    upper: list = []
    for q in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1], np.float64)


def silhouette(box: VirtualBox, cam: Camera) -> np.ndarray | None:
    """(M, 2) convex polygon (pixel coordinates, counter-clockwise in x-right/y-down terms of the
    hull routine) the box projects to, or None when a corner is not in front of the camera (the box
    reaches behind it: no finite silhouette)."""
    uv, z = cam.project(box.corners())
    if not (z > NEAR).all() or not np.isfinite(uv).all():
        return None
    return _hull(uv)


def polygon_mask(poly: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels [x, x+1] x [y, y+1] whose square shares positive area with the convex
    polygon (M, 2), by the separating axis theorem (exact; a square only touching an edge or a
    corner is outside)."""
    mask = np.zeros((height, width), bool)
    if poly is None or len(poly) < 3:
        return mask
    x0 = max(0, int(np.floor(poly[:, 0].min())))
    x1 = min(width, int(np.ceil(poly[:, 0].max())))
    y0 = max(0, int(np.floor(poly[:, 1].min())))
    y1 = min(height, int(np.ceil(poly[:, 1].max())))
    if x0 >= x1 or y0 >= y1:
        return mask
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    # image axes: the bounding-box test (strict, so touching is outside)
    inside = (xs + 1 > poly[:, 0].min()) & (xs < poly[:, 0].max())
    inside &= (ys + 1 > poly[:, 1].min()) & (ys < poly[:, 1].max())
    centroid = poly.mean(axis=0)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        e = b - a
        n = np.array([e[1], -e[0]])
        if n @ (centroid - a) > 0:
            n = -n  # outward
        # the square's corner that lies furthest against n: min over corners of n . (c - a)
        lo = n[0] * xs + n[1] * ys + min(0.0, n[0]) + min(0.0, n[1]) - n @ a
        inside &= lo < 0
    mask[y0:y1, x0:x1] = inside
    return mask


def footprint_mask(box: VirtualBox, cam: Camera) -> np.ndarray | None:
    """(H, W) bool: every pixel whose square any ray of the box hits (module doc); None when the box
    reaches behind the camera."""
    poly = silhouette(box, cam)
    return None if poly is None else polygon_mask(poly, cam.width, cam.height)


def coverage(box: VirtualBox, cam: Camera) -> tuple[float, bool]:
    """(fraction of the image the silhouette covers (polygon area, clipped to the image), whether
    the whole silhouette lies inside the image); (nan, False) when the box reaches behind the
    camera. Cheap: no rasterisation (used to search placements)."""
    import cv2

    poly = silhouette(box, cam)
    if poly is None:
        return float("nan"), False
    W, H = cam.width, cam.height
    frame = np.array([[0, 0], [W, 0], [W, H], [0, H]], np.float32)
    area, _ = cv2.intersectConvexConvex(poly.astype(np.float32), frame)
    whole = bool((poly[:, 0] >= 0).all() and (poly[:, 0] <= W).all() and (poly[:, 1] >= 0).all()
                 and (poly[:, 1] <= H).all())  # fmt: skip
    return max(0.0, float(area)) / (W * H), whole


# ------------------------------------------------------------------------------------- ray casting


def rays(cam: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and world directions (N, 3) scaled so their camera z is 1 (t = camera depth)."""
    x = (np.asarray(u, np.float64) - cam.K[0, 2]) / cam.K[0, 0]
    y = (np.asarray(v, np.float64) - cam.K[1, 2]) / cam.K[1, 1]
    c2w = cam.camtoworld
    return c2w[:3, 3], np.stack([x, y, np.ones_like(x)], axis=1) @ c2w[:3, :3].T


def intersect(box: VirtualBox, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays o (3,) + t d (N, 3) -> entry t (N,) (inf on a miss or when the origin is inside) and the
    face hit (N,) as 2 * axis + (1 if the +axis face); slab method in the box frame."""
    ol = (o - box.center) @ box.axes
    dl = d @ box.axes
    h = box.size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dl) < 1e-15, 1e-15, dl)
    t1 = (-h - ol) * inv
    t2 = (h - ol) * inv
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    axis = tmin.argmax(axis=1)
    t_in = tmin.max(axis=1)
    hit = (t_in <= tmax.min(axis=1)) & (t_in > 0)
    positive = dl[np.arange(len(dl)), axis] < 0  # a ray entering through the +axis face moves towards -axis
    return np.where(hit, t_in, np.inf), 2 * axis + positive


def _face_colour(
    box: VirtualBox, o: np.ndarray, d: np.ndarray, t: np.ndarray, face: np.ndarray
) -> np.ndarray:
    """(N, 3) shaded texture colour of hits (all rays given hit)."""
    p = (o - box.center) @ box.axes + t[:, None] * (d @ box.axes)
    h = box.size / 2
    rng = np.random.default_rng(box.seed)
    cells = rng.integers(0, len(PALETTE), size=(6, TEXTURE_CELLS, TEXTURE_CELLS))
    out = np.zeros((len(t), 3), np.float32)
    for f in range(6):
        sel = face == f
        if not sel.any():
            continue
        axis, positive = divmod(f, 2)
        a, b = [k for k in range(3) if k != axis]
        u = np.clip((p[sel, a] + h[a]) / (2 * h[a]), 0, 1 - 1e-9) * TEXTURE_CELLS
        v = np.clip((p[sel, b] + h[b]) / (2 * h[b]), 0, 1 - 1e-9) * TEXTURE_CELLS
        col = PALETTE[cells[f, v.astype(int), u.astype(int)]]
        fu, fv = u - np.floor(u), v - np.floor(v)
        edge = (np.minimum(fu, 1 - fu) < TEXTURE_BORDER / 2) | (np.minimum(fv, 1 - fv) < TEXTURE_BORDER / 2)
        col = np.where(edge[:, None], BORDER_COLOUR, col)
        n = np.zeros(3)
        n[axis] = 1.0 if positive else -1.0
        out[sel] = col * np.float32(AMBIENT + (1 - AMBIENT) * max(0.0, float(n @ LIGHT)))
    return out


def render_box(box: VirtualBox, cam: Camera, supersample: int = 3) -> dict[str, np.ndarray] | None:
    """The box in one view, or None when it reaches behind the camera.

    Returns mask (H, W) bool (`footprint_mask`), rgb (H, W, 3) float32 (the box's colour inside the
    mask, 0 outside; module doc), depth (H, W) float32 camera z of the box at pixel centres (inf
    where the centre ray misses it).
    """
    from scipy.ndimage import distance_transform_edt

    mask = footprint_mask(box, cam)
    if mask is None:
        return None
    H, W = mask.shape
    rgb = np.zeros((H, W, 3), np.float32)
    depth = np.full((H, W), np.inf, np.float32)
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return {"mask": mask, "rgb": rgb, "depth": depth}
    acc = np.zeros((len(ys), 3), np.float32)
    hits = np.zeros(len(ys), np.int64)
    offs = (np.arange(supersample) + 0.5) / supersample
    for oy in offs:
        for ox in offs:
            o, d = rays(cam, xs + ox, ys + oy)
            t, face = intersect(box, o, d)
            ok = np.isfinite(t)
            acc[ok] += _face_colour(box, o, d[ok], t[ok], face[ok])
            hits += ok
    o, d = rays(cam, xs + 0.5, ys + 0.5)
    depth[ys, xs] = intersect(box, o, d)[0]
    got = hits > 0
    rgb[ys[got], xs[got]] = acc[got] / hits[got, None]
    if not got.all():
        if got.any():
            # slivers no ray hit: the colour of the nearest pixel that has one (still 100% box)
            have = np.zeros((H, W), bool)
            have[ys[got], xs[got]] = True
            _, (iy, ix) = distance_transform_edt(~have, return_indices=True)
            rgb[ys[~got], xs[~got]] = rgb[iy[ys[~got], xs[~got]], ix[ys[~got], xs[~got]]]
        else:  # a box smaller than a ray spacing: one shaded palette colour
            rgb[ys, xs] = PALETTE[0] * np.float32(AMBIENT + (1 - AMBIENT) * LIGHT[2])
    return {"mask": mask, "rgb": rgb, "depth": depth}


# --------------------------------------------------------------------------------------- occlusion


def occluders(box: VirtualBox, cam: Camera, points: np.ndarray, margin: float) -> int:
    """How many of the scene points (N, 3) hide part of the box in this view: points whose pixel is
    in the box's silhouette and whose camera depth is smaller than the box's along that pixel's ray
    by more than `margin` (world units). Points inside the box (grown by `margin`) are not counted
    (they are the box intersecting the scene, a separate check: `points_inside`)."""
    poly = silhouette(box, cam)
    if poly is None or len(points) == 0:
        return 0
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[~box.contains(pts, grow=margin)]
    uv, z = cam.project(pts)
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    if not ok.any():
        return 0
    uv, z = uv[ok], z[ok]
    # inside the convex silhouette: on the inner side of every edge
    centroid = poly.mean(axis=0)
    inside = np.ones(len(uv), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        e = b - a
        n = np.array([e[1], -e[0]])
        if n @ (centroid - a) > 0:
            n = -n
        inside &= (uv - a) @ n < 0
    if not inside.any():
        return 0
    o, d = rays(cam, uv[inside, 0], uv[inside, 1])
    t = intersect(box, o, d)[0]
    return int((z[inside] < t - margin).sum())


def points_inside(box: VirtualBox, points: np.ndarray, shrink: float) -> int:
    """How many scene points lie inside the box shrunk by `shrink` per side: real geometry the box
    would cut through (the base sits on noisy surface points, hence the shrink)."""
    if len(points) == 0:
        return 0
    return int(box.contains(points, grow=-shrink).sum())


def below_plane(plane: Plane, cam: Camera) -> bool:
    """The camera is on the far side of the supporting plane: it would see the box through it."""
    return bool(plane.distance(cam.center)[0] <= 0)
