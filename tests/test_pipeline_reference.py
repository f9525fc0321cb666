"""The reference view (coin_cl.pipeline.reference): the choice rule, --ref, and P_k's pixels."""

from __future__ import annotations

import numpy as np
import pytest

from coin_cl.pipeline import reference
from coin_cl.pipeline.reference import choose_reference, resolve_reference
from coin_cl.scene.types import Camera, Scene


def _masks():
    H, W = 20, 30
    small = np.zeros((H, W), bool)
    small[8:12, 13:17] = True  # central, small
    big_corner = np.zeros((H, W), bool)
    big_corner[0:10, 0:12] = True  # larger but in a corner
    big_centre = np.zeros((H, W), bool)
    big_centre[5:15, 9:21] = True  # as large, central
    return [small, big_corner, big_centre, big_centre.copy(), np.zeros((H, W), bool)]


def test_choose_reference_rule():
    ms = _masks()
    assert reference.reference_score(ms[2]) > reference.reference_score(ms[1]) > 0
    assert reference.reference_score(ms[4]) == 0.0
    assert choose_reference(ms) == 2  # ties (2 and 3) go to the lowest index
    assert choose_reference(ms, train_idx=[0, 1, 3, 4]) == 3
    assert choose_reference(ms, train_idx=[0, 1]) == 1  # 0.2 x 0.43 beats 0.027 x 0.99


def test_choose_reference_from_scene_and_resolve():
    ms = _masks()
    cams = [Camera(K=np.eye(3), viewmat=np.eye(4), width=30, height=20, name=f"img_{i:03d}.png")
            for i in range(5)]  # fmt: skip
    scene = Scene(cams, [np.zeros((20, 30, 3), np.float32)] * 5, ms, np.zeros((0, 3)),
                  train_idx=[0, 1, 3, 4], test_idx=[2])  # fmt: skip
    assert choose_reference(scene) == 3
    assert choose_reference(scene, ref="img_001.png") == 1
    assert choose_reference(scene, ref="img_001") == 1
    assert choose_reference(scene, ref=4) == 4
    assert choose_reference(scene, ref="0") == 0
    with pytest.raises(ValueError, match="not a training view"):
        choose_reference(scene, ref=2)
    with pytest.raises(ValueError, match="no view of that name"):
        choose_reference(scene, ref="nope.png")
    with pytest.raises(ValueError, match="not a training view"):
        resolve_reference(17, scene.names, scene.train_idx)
    with pytest.raises(ValueError):
        resolve_reference(1.5, scene.names, scene.train_idx)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# P_k


@pytest.fixture(scope="module")
def room():
    from coin_cl.scene.synthetic import make_synthetic

    s = make_synthetic(n_views=8, width=128, height=96, n_points=2000)
    k = next(i for i in range(len(s.cameras)) if not s.is_test[i])
    return s, k


def test_reference_points_match_ground_truth(room):
    s, k = room
    cam = s.cameras[k]
    pts = reference.reference_points(cam, s.depth_absent[k], s.masks[k], margin_px=0)
    assert len(pts) == int(s.masks[k].sum())  # every masked pixel has a finite depth in the room
    uv, z = cam.project(pts)
    ys, xs = np.nonzero(s.masks[k])
    np.testing.assert_allclose(uv, np.stack([xs + 0.5, ys + 0.5], 1), atol=1e-3)
    np.testing.assert_allclose(z, s.depth_absent[k][ys, xs], rtol=1e-5)
    wide = reference.reference_points(cam, s.depth_absent[k], s.masks[k])
    assert len(wide) > len(pts)  # the default margin adds a ring
    with pytest.raises(ValueError, match="must be the camera"):
        reference.reference_points(cam, s.depth_absent[k][:-1], s.masks[k])


def test_pk_margin_and_pixels():
    m = np.zeros((60, 80), bool)
    assert reference.pk_margin_px(m) == 4  # empty mask: the floor
    m[10:20, 10:15] = True
    assert reference.pk_margin_px(m) == 4  # 10 % of 10 px is below the floor
    m[10:50, 10:70] = True
    assert reference.pk_margin_px(m) == 6  # 10 % of the larger side, 60 px
    depth = np.full(m.shape, 2.0)
    depth[12, 12] = np.nan
    depth[13, 13] = -1.0
    ys, xs = reference.reference_pixels(depth, m, margin_px=0)
    assert len(ys) == int(m.sum()) - 2 and not ((ys == 12) & (xs == 12)).any()
    valid = np.zeros(m.shape, bool)
    valid[:30] = True
    ys_v, _ = reference.reference_pixels(depth, m, 0, valid)
    assert (ys_v < 30).all() and len(ys_v) < len(ys)
    ys_m, xs_m = reference.reference_pixels(depth, m, 3)
    assert ys_m.min() == 7 and xs_m.max() == 72  # dilated by 3 px on every side
    with pytest.raises(ValueError, match="margin_px"):
        reference.reference_pixels(depth, m, -1)
    with pytest.raises(ValueError, match="differ"):
        reference.reference_pixels(depth[:-1], m)
