"""Masks: reading, the SPIn-NeRF size quirk, derived kinds, validation."""

import logging

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from coin_cl.scene.masks import (
    auto_dilation,
    bbox,
    bbox_mask,
    check_mask,
    derive_mask,
    dilate_mask,
    read_mask,
    scribble_mask,
)


def _blob(rng, H=48, W=64):
    m = np.zeros((H, W), bool)
    y, x = rng.integers(10, H - 20), rng.integers(10, W - 20)
    m[y : y + rng.integers(4, 12), x : x + rng.integers(4, 12)] = True
    m[y + 2, x - 3 : x] = True  # make it non-rectangular
    return m


@pytest.mark.parametrize("value", [1, 255])
def test_read_mask_01_and_0255(tmp_path, value):
    m = _blob(np.random.default_rng(value))
    p = tmp_path / "m.png"
    iio.imwrite(p, m.astype(np.uint8) * value)
    np.testing.assert_array_equal(read_mask(p, m.shape), m)
    rgb = tmp_path / "rgb.png"
    iio.imwrite(rgb, np.repeat(m[..., None].astype(np.uint8) * value, 3, axis=2))
    np.testing.assert_array_equal(read_mask(rgb), m)


def test_taller_test_mask_is_cropped_and_other_mismatch_names_file(tmp_path):
    rng = np.random.default_rng(5)
    tall = np.zeros((57, 64), np.uint8)
    tall[:48] = _blob(rng)
    tall[50:] = 1  # the extra rows must be dropped, not kept
    p = tmp_path / "out_00001.png"
    iio.imwrite(p, tall)
    m = read_mask(p, (48, 64))
    assert m.shape == (48, 64)
    np.testing.assert_array_equal(m, tall[:48] > 0)
    with pytest.raises(ValueError, match=r"out_00001\.png.*64x57.*64x40"):
        read_mask(p, (40, 64))
    with pytest.raises(FileNotFoundError, match="nope.png"):
        read_mask(tmp_path / "nope.png")


def test_bbox_mask_by_hand():
    m = np.zeros((6, 8), bool)
    m[1, 2] = m[3, 5] = True
    assert bbox(m) == (1, 4, 2, 6)
    want = np.zeros((6, 8), bool)
    want[1:4, 2:6] = True
    np.testing.assert_array_equal(bbox_mask(m), want)
    want_pad = np.zeros((6, 8), bool)
    want_pad[0:5, 1:7] = True
    np.testing.assert_array_equal(bbox_mask(m, pad=1), want_pad)
    assert bbox(np.zeros((3, 3), bool)) is None
    assert not bbox_mask(np.zeros((3, 3), bool)).any()


def test_dilation_matches_spinnerf_kernel():
    m = np.zeros((41, 41), bool)
    m[20, 20] = True
    d = dilate_mask(m)  # 5x5 kernel, 5 iterations: a single pixel grows 2 px per iteration
    ys, xs = np.nonzero(d)
    assert (ys.min(), ys.max(), xs.min(), xs.max()) == (10, 30, 10, 30)
    rng = np.random.default_rng(6)
    b = _blob(rng)
    ref = cv2.dilate(b.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=5) > 0
    np.testing.assert_array_equal(dilate_mask(b), ref)


def test_auto_dilation_covers_an_objects_fringe():
    """The default ring: 8 px at SPIn-NeRF's half size, 2 px (the least) on small images; a 1-px
    antialiased fringe and a 6-px contact shadow of a 504x284 object lie inside the dilated mask."""
    sizes = [(504, 284), (1008, 567), (192, 144), (8, 6)]
    assert [auto_dilation(w, h) for w, h in sizes] == [4, 7, 1, 1]
    label = np.zeros((284, 504), bool)
    label[100:180, 200:320] = True
    fringe = cv2.dilate(label.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~label
    shadow = np.zeros_like(label)
    shadow[180:186, 200:320] = True  # below the object, 6 px
    m = derive_mask(label, "seg", dilate=auto_dilation(504, 284))
    assert m[fringe].all() and m[shadow].all()
    assert not derive_mask(label, "seg", dilate=0)[fringe].any()
    assert m.sum() < 1.5 * label.sum()  # a ring, not a new region


def test_scribble_is_seeded_superset():
    rng = np.random.default_rng(7)
    m = _blob(rng, 96, 128)
    a = scribble_mask(m, seed=3)
    b = scribble_mask(m, seed=3)
    c = scribble_mask(m, seed=4)
    np.testing.assert_array_equal(a, b)
    assert (a & m).sum() == m.sum()  # keeps the object
    assert a.sum() > m.sum() * 1.2  # adds irregular strokes
    assert not np.array_equal(a, c)
    # and it is not just the box
    assert not np.array_equal(a, bbox_mask(a))


def test_derive_mask_kinds():
    m = _blob(np.random.default_rng(8))
    np.testing.assert_array_equal(derive_mask(m, "seg"), m)
    np.testing.assert_array_equal(derive_mask(m, "bbox"), bbox_mask(m))
    np.testing.assert_array_equal(derive_mask(m, "seg", dilate=5), dilate_mask(m))
    with pytest.raises(ValueError, match="unknown mask kind"):
        derive_mask(m, "circle")


def test_check_mask_empty_warns_and_full_raises(caplog):
    with caplog.at_level(logging.WARNING):
        out = check_mask(np.zeros((4, 4), bool), source="label/a.png")
    assert not out.any()
    assert "label/a.png" in caplog.text and "empty" in caplog.text
    with pytest.raises(ValueError, match="label/b.png.*whole image"):
        check_mask(np.ones((4, 4), bool), source="label/b.png")


def test_jpeg_mask_reads_as_the_saved_mask(tmp_path):
    """A 0/255 mask saved as JPEG has values near 0 and 255 (ringing, noise); the half-range
    threshold reads it back (up to the blurred edge pixels), where `> 0` would speckle it."""
    m = np.zeros((48, 64), bool)
    m[10:30, 20:44] = True
    p = tmp_path / "m.jpg"
    iio.imwrite(p, m.astype(np.uint8) * 255, extension=".jpg", quality=75)
    raw = iio.imread(p)
    assert ((raw > 0) != m).sum() > 20  # the file really holds off values near 0 (else no test)
    assert (read_mask(p, m.shape) != m).sum() <= 4


def test_unreadable_mask_names_file(tmp_path):
    p = tmp_path / "label" / "v.png"
    p.parent.mkdir()
    p.write_bytes(b"\x89PNG\r\n\x1a\n broken")
    with pytest.raises(ValueError, match=r"mask .*v\.png cannot be read"):
        read_mask(p)
