"""2D inpainting: source order, paste-back, crops, and the stiff cases (empty/full mask, borders, NaN)."""

import logging

import numpy as np
import pytest
import torch
from coin_cl.diffusion.inpaint2d import (
    InpaintConfig,
    crop_box,
    feather_weights,
    inpaint_image,
    opencv_inpaint,
    paste,
)

from coin_cl.crop import crop_image


class _ConstModel:
    """A fake model: fills the crop with a constant; records what it was given."""

    work_size = 32
    name = "fake"

    def __init__(self):
        self.calls = []

    def inpaint(self, image, mask, prompt="", cfg=None, energy=None, generator=None):
        self.calls.append((image.shape, mask.shape, float(mask.mean())))
        return torch.full_like(image, 0.25)


def _img(h=48, w=64, seed=0):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


def test_empty_mask_returns_input_and_logs(caplog):
    img = _img()
    with caplog.at_level(logging.INFO):
        out, src = inpaint_image(img, np.zeros(img.shape[:2], bool))
    assert np.array_equal(out, img) and src == "none (empty mask)" and "empty mask" in caplog.text


def test_full_mask_and_nan_are_clear_errors():
    img = _img()
    with pytest.raises(ValueError, match="whole image: nothing to condition"):
        inpaint_image(img, np.ones(img.shape[:2], bool))
    img[5, 6, 1] = np.nan
    m = np.zeros(img.shape[:2], bool)
    m[10:20, 10:20] = True
    with pytest.raises(ValueError, match="NaN"):
        inpaint_image(img, m)
    with pytest.raises(ValueError, match="mask shape"):
        inpaint_image(_img(), np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="uint8"):
        inpaint_image((_img() * 255).astype(np.uint8), m)


@pytest.mark.parametrize("method", ["telea", "ns", "fsr_fast"])
def test_opencv_fallback_named_and_outside_identical(method, caplog):
    img = _img()
    m = np.zeros(img.shape[:2], bool)
    m[0:12, 50:64] = True  # touches top and right borders
    with caplog.at_level(logging.WARNING):
        out, src = inpaint_image(img, m, cfg=InpaintConfig(opencv_method=method))
    assert src == f"OpenCV classical inpainting ({method})" and src in caplog.text
    assert np.array_equal(out[~m], img[~m]) and np.isfinite(out).all()
    # the fill is a smooth interpolation of the surroundings: within the range of the image
    assert out[m].min() >= 0 and out[m].max() <= 1


def test_source_order_dataset_before_prior():
    img = _img()
    m = np.zeros(img.shape[:2], bool)
    m[20:30, 20:30] = True
    ds = np.full_like(img, 0.7)
    model = _ConstModel()
    out, src = inpaint_image(img, m, dataset_inpaint=ds, scene_prior=model, cfg=InpaintConfig(feather_px=0))
    assert src == "dataset per-view inpaint" and not model.calls
    assert np.allclose(out[m], 0.7) and np.array_equal(out[~m], img[~m])
    out, src = inpaint_image(img, m, scene_prior=model, cfg=InpaintConfig(feather_px=0))
    assert src == "scene prior" and model.calls[-1][0] == (1, 3, 32, 32)
    assert np.allclose(out[m], 0.25, atol=1e-6)
    with pytest.raises(ValueError, match="dataset inpaint shape"):
        inpaint_image(img, m, dataset_inpaint=ds[:10])


@pytest.mark.parametrize("box", [(0, 10, 0, 10), (38, 48, 54, 64), (0, 48, 30, 34)])
def test_border_masks_and_crop_larger_than_image(box):
    img = _img()
    m = np.zeros(img.shape[:2], bool)
    m[box[0] : box[1], box[2] : box[3]] = True
    model = _ConstModel()
    model.work_size = 128  # crop (128) larger than the 48x64 image: padded by reflection
    out, src = inpaint_image(img, m, scene_prior=model, cfg=InpaintConfig(feather_px=2))
    assert np.array_equal(out[~m], img[~m])
    w = feather_weights(m, 2)
    # fully-weighted pixels are the fill; the outer ring is the mean of fill and input
    assert np.allclose(out[w == 1], 0.25, atol=1e-6)
    ring = w == 0.5
    assert np.allclose(out[ring], 0.5 * 0.25 + 0.5 * img[ring], atol=1e-6)
    assert model.calls[-1][2] < 1.0  # the model saw some known context


def test_crop_box_centred_and_inside():
    m = np.zeros((600, 1000), bool)
    m[100:200, 700:900] = True
    y0, x0, side = crop_box(m, 512, 1.5)
    assert side == 512 and 0 <= y0 and y0 + side <= 600 and 0 <= x0 and x0 + side <= 1000
    assert x0 <= 700 and x0 + side >= 900  # the mask is inside the crop
    m2 = np.zeros((40, 40), bool)
    m2[5:10, 5:10] = True
    y0, x0, side = crop_box(m2, 64, 1.5)
    c = crop_image(np.arange(1600).reshape(40, 40), y0, x0, side, side)
    assert c.shape == (64, 64) and y0 < 0 and x0 < 0


def test_opencv_bad_method():
    with pytest.raises(ValueError, match="opencv_method"):
        opencv_inpaint(_img(), np.ones((48, 64), bool), "lama")


@pytest.mark.parametrize("shape", [(70, 96), (64, 101)])
def test_fsr_fills_holes_at_the_bottom_and_right_border(shape):
    """OpenCV's FSR leaves the last (size mod 16) rows/columns of a hole at its YCrCb zero, RGB
    (0, 135, 0); opencv_inpaint pads the image to its block grid so they are reconstructed."""
    H, W = shape
    y, x = np.mgrid[0:H, 0:W]
    img = np.stack(
        [0.5 + 0.3 * np.sin(x / 5), 0.4 + 0.2 * np.cos(y / 7), 0.6 + 0.2 * np.sin((x + y) / 9)], -1
    )
    img = img.astype(np.float32)  # R >= 0.2 and B >= 0.4 everywhere
    for box in (
        (slice(H - 30, H), slice(30, 60)),
        (slice(20, 50), slice(W - 25, W)),
        (slice(H - 25, H), slice(W - 25, W)),
    ):
        m = np.zeros((H, W), bool)
        m[box] = True
        fill = opencv_inpaint(img, m, "fsr_fast")[m]
        assert not ((fill[:, 0] < 0.1) & (fill[:, 2] < 0.1)).any(), box


def test_paste_on_an_exact_mask_blends_toward_the_surroundings_not_the_object():
    """A mask ending at the object's edge: feathered toward the image, the ring keeps half the object's
    colour (an outline); toward the surroundings continued inward, none of it. Outside the mask both
    are the image, bit for bit; a hard paste (feather 0) is the same either way."""
    img = np.full((40, 50, 3), 0.6, np.float32)
    img[10:30, 15:35] = (0.0, 0.0, 1.0)  # the object: pure blue on grey
    m = np.zeros((40, 50), bool)
    m[10:30, 15:35] = True  # exact: every masked pixel is the object
    fill = np.full_like(img, 0.5)
    ring = feather_weights(m, 2) == 0.5
    outline = paste(img, fill, m, 2)
    assert np.allclose(outline[ring][:, 2], 0.5 * 0.5 + 0.5 * 1.0)  # half of the object's blue
    clean = paste(img, fill, m, 2, edge="surroundings")
    assert np.array_equal(clean[~m], img[~m])
    assert np.abs(clean[m] - 0.55).max() < 0.06  # between the fill (0.5) and the grey around (0.6)
    assert np.array_equal(paste(img, fill, m, 0, edge="surroundings"), paste(img, fill, m, 0))
    with pytest.raises(ValueError, match="edge must be one of"):
        paste(img, fill, m, 2, edge="object")
