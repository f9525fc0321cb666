"""The embedded exemplar inpainter (coin_cl.diffusion.exemplar) on problems with a known answer: a
periodic texture it must continue, the demo room's textures (exact truth behind the object) against
OpenCV Telea on GMSD and SWD, determinism, and the degenerate inputs."""

import cv2
import numpy as np
import pytest
from coin_cl.diffusion.exemplar import ExemplarConfig, exemplar_inpaint
from coin_cl.diffusion.inpaint2d import opencv_inpaint

from coin_cl import metrics as M


def _periodic(H=72, W=88):
    y, x = np.mgrid[0:H, 0:W]
    r = 0.5 + 0.4 * np.sin(2 * np.pi * x / 8) * np.cos(2 * np.pi * y / 6)
    g = 0.5 + 0.3 * np.sin(2 * np.pi * (x + y) / 11)
    return np.stack([r, g, 1 - r], axis=-1).astype(np.float32)


def _hole(H=72, W=88):
    m = np.zeros((H, W), bool)
    m[26:46, 34:56] = True
    return m


def test_continues_a_periodic_texture():
    img, m = _periodic(), _hole()
    out = exemplar_inpaint(img, m, ExemplarConfig(mode="full"), seed=0)
    np.testing.assert_array_equal(out[~m], img[~m])  # outside the mask bit-identical
    tel = opencv_inpaint(img, m, "telea")
    assert M.masked_psnr(out, img, m) > 30 > M.masked_psnr(tel, img, m)
    assert M.swd(out, img, m) < 0.5 * M.swd(tel, img, m)
    # "hf" keeps the smooth solver's low band (wrong here: the period is longer than hf_sigma) and
    # adds the synthesis's high band: more texture-like than Telea, not exact
    hf = exemplar_inpaint(img, m, ExemplarConfig(mode="hf"), seed=0)
    assert M.swd(hf, img, m) < M.swd(tel, img, m)


def test_room_textures_beat_telea_on_gmsd_and_swd():
    from coin_cl.scene.synthetic import make_synthetic

    s = make_synthetic(n_views=4, width=160, height=120, seed=0, n_points=500)
    res = {"ex": [], "telea": []}
    for i in range(4):
        truth, m = s.absent[i].astype(np.float32), s.masks[i]
        srcs = [(s.present[j].astype(np.float32), s.masks[j]) for j in range(4) if j != i]
        res["ex"].append(exemplar_inpaint(truth, m, seed=0, sources=srcs))
        res["telea"].append(opencv_inpaint(truth, m, "telea"))
    score = {
        k: (np.mean([M.bbox_gmsd(o, s.absent[i], s.masks[i]) for i, o in enumerate(v)]),
            np.mean([M.swd(o, s.absent[i], s.masks[i]) for i, o in enumerate(v)]))
        for k, v in res.items()
    }  # fmt: skip
    assert score["ex"][0] < score["telea"][0], score
    assert score["ex"][1] < score["telea"][1], score


def test_deterministic_for_a_seed():
    rng = np.random.default_rng(3)
    img = np.clip(_periodic() + rng.normal(0, 0.05, (72, 88, 3)), 0, 1).astype(np.float32)
    m = _hole()
    a = exemplar_inpaint(img, m, seed=5)
    np.testing.assert_array_equal(a, exemplar_inpaint(img, m, seed=5))
    assert not np.array_equal(a, exemplar_inpaint(img, m, seed=6))


def test_degenerate_inputs():
    img, m = _periodic(), _hole()
    np.testing.assert_array_equal(exemplar_inpaint(img, np.zeros_like(m)), img)  # empty mask
    with pytest.raises(ValueError, match="whole image"):
        exemplar_inpaint(img, np.ones_like(m))
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        exemplar_inpaint(bad, m)
    thin = np.ones((8, 40), bool)  # 8 px tall, no fully known 7x7 patch anywhere
    thin[:, :4] = False
    with pytest.raises(ValueError, match="no fully known patch"):
        exemplar_inpaint(np.full((8, 40, 3), 0.5, np.float32), thin)
    with pytest.raises(ValueError, match="odd"):
        ExemplarConfig(patch=6)
    with pytest.raises(ValueError, match="sources must match"):
        exemplar_inpaint(img, m, sources=[(img[:10], m[:10])])
    out = exemplar_inpaint(img[:, :, :3], m, ExemplarConfig(min_coarse=1000))  # one level only
    assert np.isfinite(out).all()


def test_no_dark_holes_where_matches_are_poor():
    """Every filled pixel is a mean of copied pixels: with no dark value in the image the fill has none.
    A smooth background (tiny patch distances, so a tiny median) and a noise strip through the hole
    (no good match) once made the vote's weights underflow to 0/0: black pixels in real fills."""
    rng = np.random.default_rng(0)
    H, W = 96, 120
    x = np.mgrid[0:H, 0:W][1]
    img = np.repeat((0.45 + 0.1 * x / W)[..., None], 3, axis=2).astype(np.float32)
    img[:, 55:65] = (0.3 + 0.6 * rng.random((H, 10, 3))).astype(np.float32)
    m = np.zeros((H, W), bool)
    m[30:66, 35:85] = True
    for mode in ("full", "hf"):
        out = exemplar_inpaint(img, m, ExemplarConfig(mode=mode), seed=0)
        assert out[m].min() > 0.2, mode


def test_texture_gain_matches_the_windows_band_within_its_bounds():
    from coin_cl.diffusion.exemplar import texture_gain

    rng = np.random.default_rng(0)
    win = np.clip(0.5 + 0.1 * rng.standard_normal((48, 48, 3)), 0, 1).astype(np.float32)
    hole = np.zeros((48, 48), bool)
    hole[16:32, 16:32] = True
    cfg = ExemplarConfig(texture_gain_max=4.0)
    band = win - cv2.GaussianBlur(win, (0, 0), cfg.hf_sigma)
    # a synthesised band of half the window's strength is brought back by a gain of about 2
    assert texture_gain(win, hole, 0.5 * band, cfg) == pytest.approx(2.0, rel=0.15)
    # capped, never below hf_gain, off when the cap is not above hf_gain
    assert texture_gain(win, hole, 0.1 * band, ExemplarConfig(texture_gain_max=2.0)) == 2.0
    assert texture_gain(win, hole, 3.0 * band, cfg) == cfg.hf_gain
    assert texture_gain(win, hole, 0.5 * band, ExemplarConfig()) == ExemplarConfig().hf_gain
    # degenerate: a flat band in the hole, a flat window, an empty hole -> hf_gain, never NaN
    assert texture_gain(win, hole, 0 * band, cfg) == cfg.hf_gain
    flat = np.full_like(win, 0.3)
    assert texture_gain(flat, hole, 0.5 * band, cfg) == cfg.hf_gain
    assert texture_gain(win, np.zeros_like(hole), band, cfg) == cfg.hf_gain
    for bad in (dict(vote="median"), dict(texture_gain_max=float("nan"))):
        with pytest.raises(ValueError):
            ExemplarConfig(**bad)
