"""Crop cameras (coin_cl.crop): the cropped intrinsics agree with what cv2's crop + resize do
to the pixels, and the reflect-padded crop."""

from __future__ import annotations

import cv2
import numpy as np

from coin_cl.crop import crop_image, crop_intrinsics, resize_to
from coin_cl.scene.types import Camera


def test_crop_intrinsics_follow_the_pixels():
    K = np.array([[50.0, 0, 40.0], [0, 50.0, 30.0], [0, 0, 1]])
    cam = Camera(K, np.eye(4), 80, 60)
    img = np.zeros((60, 80), np.float32)
    img[10:12, 20:22] = 1.0  # a 2x2 block whose centre is (u, v) = (21, 11)
    point = cam.unproject(np.array([[21.0, 11.0]]), np.array([3.0]))
    y0, x0, side = 2, 4, 32
    small = resize_to(crop_image(img, y0, x0, side, side), side // 2, side // 2)  # area average
    row, col = np.unravel_index(np.argmax(small), small.shape)
    assert small[row, col] == 1.0  # the block fell on exactly one output pixel
    crop_cam = Camera(crop_intrinsics(K, x0, y0, 0.5, 0.5), np.eye(4), side // 2, side // 2)
    px, ok = crop_cam.pixels(point)
    assert ok[0] and (px[0, 1], px[0, 0]) == (row, col)
    uv, _ = crop_cam.project(point)
    np.testing.assert_allclose(uv[0], [(21 - x0) * 0.5, (11 - y0) * 0.5])


def test_crop_image_reflects_beyond_the_border():
    a = np.arange(16).reshape(4, 4)
    assert np.array_equal(crop_image(a, 1, 1, 2, 3), a[1:3, 1:4])
    out = crop_image(a, -1, -1, 3, 3)
    assert np.array_equal(out, [[0, 0, 1], [0, 0, 1], [4, 4, 5]])  # symmetric padding
    rgb = np.dstack([a, a, a])
    assert crop_image(rgb, 2, 2, 4, 4).shape == (4, 4, 3)


def test_resize_nearest_invents_no_value():
    d = np.array([[1.0, 1.0, 9.0, 9.0]] * 4, np.float32)
    up = resize_to(d, 8, 8, nearest=True)
    assert set(np.unique(up)) == {1.0, 9.0}
    assert resize_to(d, 4, 4) is d  # same size: untouched
    area = resize_to(d, 2, 2)
    assert np.allclose(area, cv2.resize(d, (2, 2), interpolation=cv2.INTER_AREA))
