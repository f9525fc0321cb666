"""The virtual box's geometry on the synthetic room, where the truth is known: exact footprints,
100%-box pixels, the plane fit, and the occlusion test against ray-cast room depth."""

import numpy as np
import pytest

from coin_cl.scene.synthetic import make_synthetic
from coin_cl.scene.types import Camera
from coin_cl.scene.virtual_object import (
    Plane,
    VirtualBox,
    box_on_plane,
    fit_plane,
    footprint_mask,
    intersect,
    occluders,
    rays,
    render_box,
    silhouette,
)

TABLE = Plane(np.array([0.0, 0.0, 1.0]), 0.5)  # the room's table top (z = 0.5)
FLOOR = Plane(np.array([0.0, 0.0, 1.0]), 0.0)


@pytest.fixture(scope="module")
def room():
    # the room without its object: truth for what is behind a virtual box
    return make_synthetic(n_views=8, width=96, height=72, seed=0, n_points=6000, supersample=1)


def _clip_area(poly: np.ndarray, x: float, y: float) -> float:
    """Exact area of the unit square at (x, y) inside a convex polygon (Sutherland-Hodgman, float64):
    an implementation independent of the separating-axis test under test."""
    out = [(x, y), (x + 1, y), (x + 1, y + 1), (x, y + 1)]
    c = poly.mean(axis=0)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n = np.array([b[1] - a[1], a[0] - b[0]])
        if n @ (c - a) < 0:
            n = -n  # inward
        inp, out = out, []
        for k in range(len(inp)):
            p, q = np.array(inp[k]), np.array(inp[(k + 1) % len(inp)])
            dp, dq = n @ (p - a), n @ (q - a)
            if dp >= 0:
                out.append(tuple(p))
            if (dp >= 0) != (dq >= 0):
                out.append(tuple(p + (q - p) * dp / (dp - dq)))
        if not out:
            return 0.0
    P = np.array(out)
    return 0.5 * abs(np.dot(P[:, 0], np.roll(P[:, 1], -1)) - np.dot(P[:, 1], np.roll(P[:, 0], -1)))


def _absent_points(room, per_view=800) -> np.ndarray:
    """Surface points of the room without its object (what a capture of it would triangulate)."""
    rng = np.random.default_rng(1)
    out = []
    for cam, depth in zip(room.cameras, room.depth_absent):
        yy, xx = rng.integers(0, cam.height, per_view), rng.integers(0, cam.width, per_view)
        out.append(cam.unproject(np.stack([xx + 0.5, yy + 0.5], 1), depth[yy, xx].astype(np.float64)))
    return np.concatenate(out)


def _box(seed=0) -> VirtualBox:
    return box_on_plane(TABLE, [0.35, 0.2, 0.5], [0.25, 0.2, 0.2], yaw_deg=31.0, seed=seed)


def test_mask_equals_the_exact_footprint(room):
    box = _box()
    for cam in room.cameras[:4]:
        mask = footprint_mask(box, cam)
        poly = silhouette(box, cam)
        assert mask.any()
        x0, x1 = int(np.floor(poly[:, 0].min())) - 1, int(np.ceil(poly[:, 0].max())) + 1
        y0, y1 = int(np.floor(poly[:, 1].min())) - 1, int(np.ceil(poly[:, 1].max())) + 1
        truth = np.zeros_like(mask)
        for y in range(max(0, y0), min(cam.height, y1)):
            for x in range(max(0, x0), min(cam.width, x1)):
                truth[y, x] = _clip_area(poly, x, y) > 1e-12
        assert (mask != truth).sum() == 0  # 0 pixels outside the footprint, none of it missed
        # and every pixel any of 8 x 8 rays of the box hits is in it (dense ray casting)
        H, W = mask.shape
        ys, xs = np.mgrid[0:H, 0:W]
        hit = np.zeros(H * W, bool)
        for oy in (np.arange(8) + 0.5) / 8:
            for ox in (np.arange(8) + 0.5) / 8:
                o, d = rays(cam, xs.ravel() + ox, ys.ravel() + oy)
                hit |= np.isfinite(intersect(box, o, d)[0])
        assert not (hit.reshape(H, W) & ~mask).any()


def test_footprint_counts_slivers_that_sampling_misses():
    # edges between pixel centres: pixels partly covered that no pixel-centre ray sees
    cam = Camera(np.array([[50.0, 0, 8], [0, 50.0, 8], [0, 0, 1]]), np.eye(4), 16, 16)
    box = VirtualBox([0.0131, 0.0077, 2.0], np.eye(3), [0.2, 0.2, 0.2])  # seen along its up axis
    mask = footprint_mask(box, cam)
    poly = silhouette(box, cam)
    ys, xs = np.nonzero(mask)
    assert all(_clip_area(poly, x, y) > 0 for x, y in zip(xs, ys))
    centres = np.zeros_like(mask)
    o, d = rays(cam, xs + 0.5, ys + 0.5)
    centres[ys, xs] = np.isfinite(intersect(box, o, d)[0])
    assert mask.sum() > centres.sum()  # pixels only partly covered are in the mask too


def test_render_is_all_box_inside_the_mask(room):
    box = _box()
    cam = room.cameras[1]
    r = render_box(box, cam, supersample=3)
    m = r["mask"]
    assert np.isfinite(r["rgb"]).all() and (r["rgb"][m] > 0).any(axis=1).all()
    assert (r["rgb"][~m] == 0).all()
    # the texture has several colours and the faces different shading
    assert len(np.unique(np.round(r["rgb"][m], 2), axis=0)) >= 4
    with pytest.raises(ValueError, match="size"):
        VirtualBox([0, 0, 0], np.eye(3), [0.1, 0.0, 0.1])


def test_box_behind_the_camera_has_no_silhouette(room):
    cam = room.cameras[0]
    big = VirtualBox(cam.center - [0, 0, 0.5], np.eye(3), [1.0, 1.0, 1.0])  # encloses the camera
    assert silhouette(big, cam) is None and render_box(big, cam) is None


def test_plane_fit_ignores_outliers():
    rng = np.random.default_rng(0)
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    p = rng.uniform(-1, 1, (300, 2)) @ np.stack([u, v]) + 0.3 * n + rng.normal(0, 0.002, (300, 1)) * n
    outl = rng.uniform(-1, 1, (100, 3)) + [0, 0, 1.0]
    plane = fit_plane(np.concatenate([p, outl]), 0.01, toward=[0, 0, 5.0])
    assert abs(plane.normal @ n) > 0.9999 and plane.normal[2] > 0 and abs(plane.d - 0.3) < 0.005
    box = box_on_plane(plane, [0.1, 0.1, 2.0], [0.2, 0.3, 0.4], yaw_deg=10)
    assert abs(plane.distance(box.base)[0]) < 1e-9 and np.allclose(box.axes[:, 2], plane.normal)
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane(p[:2], 0.01, toward=[0, 0, 1.0])


def test_box_behind_the_table_is_found_occluded(room):
    """A box on the floor behind the table: the views in which the room's ray-cast depth is in front
    of the box over much of its footprint are exactly the views the sparse points call occluded."""
    box = box_on_plane(FLOOR, [0.0, 0.75, 0.0], [0.3, 0.15, 0.3])
    pts = _absent_points(room)
    pts = pts[pts[:, 2] > 0.01]  # the floor the box stands on is not an occluder
    flagged, truth = [], []
    for cam, depth in zip(room.cameras, room.depth_absent):
        r = render_box(box, cam, supersample=1)
        m = r["mask"] & np.isfinite(r["depth"])
        if not m.any():
            continue
        hidden = (depth[m] < r["depth"][m] - 0.03).mean()
        truth.append(hidden > 0.3)
        flagged.append(occluders(box, cam, pts, margin=0.03) >= 10)
    assert any(truth) and flagged == truth
    # on the table top in front of everything, no view is occluded
    assert all(occluders(_box(), c, pts, margin=0.02) < 10 for c in room.cameras)
