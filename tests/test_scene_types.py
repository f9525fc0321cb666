"""coin_cl.scene.types helpers: the working-resolution mask resize."""

import numpy as np

from coin_cl.scene.types import resize_mask


def test_resize_mask_is_conservative_when_shrinking():
    m = np.zeros((90, 120), bool)
    m[40, 61] = True  # one pixel: a third of a 3x3 block, not its centre
    m[10:30, 10:31] = True
    small = resize_mask(m, 40, 30)
    assert small[13, 20]  # the single pixel's block is masked (nearest neighbour lost it)
    # every block the full-resolution mask touches is masked, no other one
    touched = m.reshape(30, 3, 40, 3).any(axis=(1, 3))
    np.testing.assert_array_equal(small, touched)
    big = resize_mask(small, 80, 60)  # enlarging: nearest neighbour, each pixel in one source pixel
    np.testing.assert_array_equal(big, np.repeat(np.repeat(small, 2, 0), 2, 1))
    assert resize_mask(m, 120, 90) is m
