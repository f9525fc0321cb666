"""The one mask vote (coin_cl.scene.geometry.mask_vote_counts) and object points, on two hand-made
cameras whose answers are known pixel by pixel; and `Camera.project` / `Camera.pixels`, which it
stands on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from coin_cl.scene.geometry import mask_vote_counts, object_points
from coin_cl.scene.types import Camera, Scene

W, H, F = 40, 30, 30.0


def _cam(tx: float = 0.0) -> Camera:
    V = np.eye(4)
    V[0, 3] = tx
    return Camera(np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]), V, W, H)


def _at(cam: Camera, u: float, v: float, z: float) -> np.ndarray:
    return cam.unproject(np.array([[u, v]]), np.array([z]))[0]


def test_project_near_and_pixels():
    cam = _cam()
    pts = np.array(
        [_at(cam, 10.5, 7.5, 2.0), [0, 0, 0.005], [0, 0, -1.0], [0, 0, np.nan], _at(cam, 39.99, 3, 1.0)]
    )
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv[0], [10.5, 7.5])
    assert np.isfinite(uv[1]).all() and np.isnan(uv[2:4]).all()  # behind the camera, NaN: NaN
    uv_n, _ = cam.project(pts, near=0.01)
    assert np.isnan(uv_n[1]).all()  # in front, but before the near plane
    px, ok = cam.pixels(torch.tensor(pts, requires_grad=True), near=0.01)
    assert ok.tolist() == [True, False, False, False, True]
    assert px[0].tolist() == [10, 7] and px[4].tolist() == [39, 3]


def test_mask_votes_count_views_and_masks():
    cams = [_cam(0.0), _cam(0.2)]
    m0 = np.zeros((H, W), bool)
    m0[5:10, 8:14] = True
    m1 = np.zeros((H, W), bool)
    on = _at(cams[0], 10.5, 7.5, 2.0)  # in m0; where in view 1?
    px1, _ = cams[1].pixels(on[None])
    m1[px1[0, 1], px1[0, 0]] = True
    off = _at(cams[0], 30.5, 20.5, 2.0)  # outside both masks
    behind = np.array([0.0, 0.0, -2.0])
    seen, inside = mask_vote_counts(np.stack([on, off, behind]), cams, [m0, torch.from_numpy(m1)])
    assert seen.tolist() == [2, 2, 0] and inside.tolist() == [2, 0, 0]
    close = np.array([[0.0, 0.0, 0.005]])
    assert mask_vote_counts(close, cams[:1], [m0])[0].tolist() == [1]  # on the axis of view 0
    assert mask_vote_counts(close, cams[:1], [m0], near=0.01)[0].tolist() == [0]
    with pytest.raises(ValueError, match="2 cameras but 1 masks"):
        mask_vote_counts(close, cams, [m0])
    with pytest.raises(ValueError, match="view 1"):
        mask_vote_counts(close, cams, [m0, m1[:-1]])
    scene = Scene(cams, [np.zeros((H, W, 3), np.float32)] * 2, [m0, m1], np.stack([on, off, behind]),
                  train_idx=[0, 1])  # fmt: skip
    assert object_points(scene, min_views=2, min_frac=1.0).tolist() == [0]
