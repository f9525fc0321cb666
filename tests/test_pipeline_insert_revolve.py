"""The revolve profile of a one-photo insertion (coin_cl.pipeline.insert_revolve): a cup-like
truncated cone (radius 0.5 at its foot, 0.7 at its top, 2 high) standing on the ground z = 0, its
left half red and its right half blue, its top green, photographed from 35 degrees above. Lifted
from that one photo, the solid must stand where the true one stands and cover its projection from
the side, from behind and from above, with its colours where the true ones are."""

import numpy as np
import pytest

from coin_cl.pipeline.insert_config import InsertConfig
from coin_cl.pipeline.insert_geometry import footprint, lift_one_photo, splat_colors, splat_depth
from coin_cl.testing import camera_looking_at

CFG = InsertConfig(regions="derive", profile="revolve")
R_FOOT, R_TOP, HEIGHT = 0.5, 0.7, 2.0


def look_at(eye, target, width: int = 160, height: int = 160, f: float = 150.0):
    return camera_looking_at(eye, target, width, height, f)


def cone(step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The true object's surface: points [N, 3] and colours [N, 3] (wall and top disc)."""
    hs = np.arange(0.0, HEIGHT + 1e-9, step)
    pts = []
    for h in hs:
        r = R_FOOT + (R_TOP - R_FOOT) * h / HEIGHT
        a = np.linspace(0, 2 * np.pi, int(2 * np.pi * r / step), endpoint=False)
        pts.append(np.stack([r * np.cos(a), r * np.sin(a), np.full(len(a), h)], 1))
    for r in np.arange(step, R_TOP, step):
        a = np.linspace(0, 2 * np.pi, max(3, int(2 * np.pi * r / step)), endpoint=False)
        pts.append(np.stack([r * np.cos(a), r * np.sin(a), np.full(len(a), HEIGHT)], 1))
    P = np.concatenate(pts)
    col = np.where((P[:, 0] < 0)[:, None], [0.9, 0.1, 0.1], [0.1, 0.1, 0.9])
    col[P[:, 2] >= HEIGHT - 1e-9] = [0.1, 0.8, 0.1]
    return P, col.astype(np.float32)


@pytest.fixture(scope="module")
def lifted():
    cam = look_at([0.0, -6.0, 4.2], [0.0, 0.0, 1.0])
    truth, colors = cone()
    img, wt = splat_colors(truth, colors, cam)
    region = footprint(truth, cam)
    edited = np.where(region[..., None], img, 0.5).astype(np.float32)
    g = np.linspace(-4, 4, 41)
    ground = np.stack([*np.meshgrid(g, g, indexing="ij"), np.zeros((41, 41))], -1).reshape(-1, 3)
    return truth, colors, lift_one_photo(edited, region, cam, ground, "cup.png", CFG)


@pytest.mark.parametrize(
    "eye",
    [[6.0, 0.0, 4.2], [0.0, 6.0, 4.2], [-4.2, 4.2, 4.2], [0.0, -1.0, 8.0]],
    ids=["side-90", "behind-180", "behind-135", "above"],
)
def test_the_solid_covers_the_true_object_from_every_side(lifted, eye):
    truth, colors, lift = lifted
    cam = look_at(eye, [0.0, 0.0, 1.0])
    true_foot, foot = footprint(truth, cam), footprint(lift.points, cam)
    recall = (foot & true_foot).sum() / true_foot.sum()
    assert recall >= 0.95, recall
    assert foot.sum() <= 1.3 * true_foot.sum(), foot.sum() / true_foot.sum()
    zt, zl = splat_depth(truth, cam), splat_depth(lift.points, cam)
    both = np.isfinite(zt) & np.isfinite(zl)
    assert np.median(np.abs(zl[both] - zt[both]) / zt[both]) < 0.03
    # the back half carries the front's colours mirrored: left red, right blue, top green
    ct, _ = splat_colors(truth, colors, cam)
    cl, _ = splat_colors(lift.points, lift.colors, cam)
    inner = both & (np.abs(ct - cl).max(-1) < 0.25)
    assert inner.sum() >= 0.8 * both.sum(), inner.sum() / both.sum()


def test_the_solid_stands_on_the_ground_and_is_round(lifted):
    _, _, lift = lifted
    P = lift.points
    assert P[:, 2].min() >= -1e-3 and abs(P[:, 2].max() - HEIGHT) < 0.1 * HEIGHT
    foot = P[P[:, 2] < 0.05]
    assert np.abs(np.linalg.norm(foot[:, :2] - foot[:, :2].mean(0), axis=1) - R_FOOT).max() < 0.1
    assert np.linalg.norm(foot[:, :2].mean(0)) < 0.1  # the axis where the true one stands
    assert abs(lift.width - 2 * R_TOP) < 0.1 * 2 * R_TOP


def test_the_shell_respects_the_point_cap(lifted):
    truth, colors, lift = lifted
    cam = look_at([0.0, -6.0, 4.2], [0.0, 0.0, 1.0])
    img, _ = splat_colors(truth, colors, cam)
    region = footprint(truth, cam)
    edited = np.where(region[..., None], img, 0.5).astype(np.float32)
    g = np.linspace(-4, 4, 41)
    ground = np.stack([*np.meshgrid(g, g, indexing="ij"), np.zeros((41, 41))], -1).reshape(-1, 3)
    cap = InsertConfig(regions="derive", profile="revolve", max_points=1000)
    small = lift_one_photo(edited, region, cam, ground, "cup.png", cap)
    assert len(small.points) <= 1000 < len(lift.points)
