"""The detail band of CLG's output (coin_cl.pipeline.clg_detail): the Laplacian split at a share of
the sampler's working size, its sources, and its exact cases."""

import numpy as np
import pytest

from coin_cl.crop import resize_to
from coin_cl.metrics import mask_texture
from coin_cl.pipeline.clg_detail import compose_crop, high_band, match_colour, texture_gain


def _texture(h=96, w=96, seed=0):
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0.2, 0.8, w, dtype=np.float32)[None, :, None] * np.ones((h, 1, 3), np.float32)
    return np.clip(ramp + 0.1 * rng.standard_normal((h, w, 3)).astype(np.float32), 0, 1)


def test_high_band_is_what_the_low_size_cannot_hold():
    img = _texture()
    assert np.array_equal(high_band(img, 96, 96), np.zeros_like(img))  # nothing above its own size
    flat = np.full((96, 96, 3), 0.4, np.float32)
    assert np.abs(high_band(flat, 16, 16)).max() < 1e-5  # a flat image has no detail
    hb = high_band(img, 16, 16)
    assert hb.std() > 0.05 and abs(float(hb.mean())) < 0.01  # the noise, zero-mean


def test_input_detail_returns_the_input_where_the_sample_matches_it():
    side, work = 96, 32
    inp = _texture(side, side)
    fill = resize_to(inp, work, work)  # a sample equal to the input at the working size
    out = compose_crop(fill, inp, 0, 0, side, "input", split=1.0)
    np.testing.assert_allclose(out, inp, atol=1e-5)
    # a sample that differs only in its low band moves the output's low band, not its detail
    shifted = compose_crop(fill + 0.1, inp, 0, 0, side, "input", split=0.5)
    np.testing.assert_allclose(high_band(shifted, 16, 16), high_band(inp, 16, 16), atol=1e-4)
    assert abs(float((shifted - inp).mean()) - 0.1) < 1e-3


def test_none_is_the_upsampled_sample_and_blurs():
    side, work = 96, 32
    inp = _texture(side, side)
    fill = resize_to(inp, work, work)
    out = compose_crop(fill, inp, 0, 0, side, "none")
    np.testing.assert_allclose(out, resize_to(fill, side, side))
    assert np.abs(np.diff(out, axis=1)).mean() < 0.6 * np.abs(np.diff(inp, axis=1)).mean()


def test_reference_detail_where_supported_input_elsewhere():
    side, work = 96, 32
    inp, ref = _texture(side, side, 0), _texture(side, side, 1)
    sup = np.zeros((side, side), bool)
    sup[:, :48] = True
    fill = resize_to(inp, work, work)
    out = compose_crop(fill, inp, 0, 0, side, "reference", (high_band(ref, 16, 16), sup), split=0.5)
    hb = high_band(out, 16, 16)
    # away from the seam, the left half carries the reference's detail and the right half the input's
    left, right = (slice(None), slice(4, 40)), (slice(None), slice(56, 92))
    assert np.corrcoef(hb[left].ravel(), high_band(ref, 16, 16)[left].ravel())[0, 1] > 0.9
    assert np.corrcoef(hb[right].ravel(), high_band(inp, 16, 16)[right].ravel())[0, 1] > 0.9
    with pytest.raises(ValueError, match="warped detail"):
        compose_crop(fill, inp, 0, 0, side, "reference")
    with pytest.raises(ValueError, match="detail must be"):
        compose_crop(fill, inp, 0, 0, side, "sharp")


def _lab_stats(img, region):
    import cv2

    lab = cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)[region]
    return lab.mean(0), lab.std(0)


def test_match_colour_moves_a_cast_to_the_target_and_never_amplifies():
    target = _texture(64, 64, 0)
    region = np.zeros((64, 64), bool)
    region[16:48, 16:48] = True
    # a purple cast and doubled colour noise: the 64 px sample's failure on the shared scene
    rng = np.random.default_rng(3)
    cast = np.clip(target * [1.1, 0.85, 1.15] + 0.1 * rng.standard_normal(target.shape), 0, 1)
    cast = cast.astype(np.float32)
    out = match_colour(cast, target, region)
    (mu_t, sd_t), (mu_c, _), (mu_o, sd_o) = (_lab_stats(a, region) for a in (target, cast, out))
    assert np.abs(mu_c - mu_t).sum() > 5  # the cast is a real one
    assert np.abs(mu_o - mu_t).sum() < 1.0 and np.abs(sd_o - sd_t).max() < 1.0
    # a flat sample is only shifted: the gain cap keeps the match from inventing variation
    flat = np.full((64, 64, 3), 0.3, np.float32)
    shifted = match_colour(flat, target, region)
    assert shifted[region].std(0).max() < 1e-3
    assert np.abs(_lab_stats(shifted, region)[0] - mu_t).sum() < 1.0
    np.testing.assert_array_equal(match_colour(cast, target, np.zeros_like(region)), cast)


def test_match_colour_with_chroma_takes_the_targets_hues_pixel_by_pixel():
    import cv2

    def lab(a):
        return cv2.cvtColor(np.clip(a, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)

    target = _texture(64, 64, 1) * np.array([0.9, 1.0, 0.8], np.float32)
    region = np.zeros((64, 64), bool)
    region[16:48, 16:48] = True
    # 8 px hue blotches on the target's lightness: what the global match leaves of a 64 px sample
    rng = np.random.default_rng(4)
    blotch = cv2.resize(rng.uniform(0.7, 1.3, (8, 8, 3)).astype(np.float32), (64, 64),
                        interpolation=cv2.INTER_NEAREST)  # fmt: skip
    sample = np.clip(target * blotch, 0, 1).astype(np.float32)
    plain, chroma = match_colour(sample, target, region), match_colour(sample, target, region, chroma=True)
    err = [np.abs(lab(a)[region][:, 1:] - lab(target)[region][:, 1:]).mean() for a in (plain, chroma)]
    assert err[0] > 3.0  # the global match keeps the blotches
    assert err[1] < 0.1 * err[0], err  # the chroma is the target's (up to the RGB round trip)
    # the lightness is still the sample's, matched to the target's mean
    assert abs(lab(chroma)[region][:, 0].mean() - lab(target)[region][:, 0].mean()) < 1.0
    assert np.corrcoef(lab(chroma)[region][:, 0], lab(sample)[region][:, 0])[0, 1] > 0.95
    # outside the region the two agree: only the region's chroma is replaced
    np.testing.assert_allclose(chroma[~region], plain[~region], atol=1e-5)


def test_compose_crop_matches_the_low_band_to_the_target_inside_the_hole():
    side, work = 96, 32
    inp = _texture(side, side, 0)
    hole = np.zeros((side, side), bool)
    hole[24:72, 24:72] = True
    tinted = resize_to(inp, work, work) * np.array([1.2, 0.8, 1.2], np.float32)  # the sample's cast
    plain = compose_crop(tinted, inp, 0, 0, side, "input", split=0.5)
    matched = compose_crop(tinted, inp, 0, 0, side, "input", split=0.5, colour=(inp, hole))
    err = [np.abs(_lab_stats(a, hole)[0] - _lab_stats(inp, hole)[0]).sum() for a in (plain, matched)]
    assert err[1] < 0.2 * err[0], err
    # the detail band is the input's either way: the match acts on the sample's band only
    np.testing.assert_allclose(high_band(matched, 16, 16)[hole], high_band(plain, 16, 16)[hole], atol=0.05)


def test_texture_gain_restores_the_inputs_texture_with_the_smallest_gain():
    side, work = 96, 32
    inp = _texture(side, side)
    hole = np.zeros((side, side), bool)
    hole[24:72, 24:72] = True
    # a sample whose low band is the input's but whose detail band is half the input's: the texture
    # lost is what the gain must bring back, and a gain near 2 does
    fill = resize_to(inp, work, work)
    weak = compose_crop(fill, 0.5 * inp + 0.5 * resize_to(resize_to(inp, 16, 16), side, side), 0, 0, side,
                        "input", split=0.5)  # fmt: skip
    t_in = mask_texture(inp, hole)

    def compose(g):
        return compose_crop(fill, 0.5 * inp + 0.5 * resize_to(resize_to(inp, 16, 16), side, side), 0, 0, side,
                            "input", split=0.5, detail_gain=g)  # fmt: skip

    tex = lambda o: mask_texture(o, hole)  # noqa: E731
    assert tex(weak) < 0.8 * t_in
    out, g = texture_gain(compose, tex, t_in, max_gain=3.0)
    assert 1.5 < g < 2.5 and tex(out) >= t_in
    assert tex(compose(g - 0.05)) < t_in  # the smallest such gain, to the bisection's step
    np.testing.assert_allclose(out, compose(g), atol=1e-6)
    # already textured enough, a non-finite target or the top-up off: the output unchanged, gain 1
    for target, top in ((0.5 * t_in, 3.0), (float("nan"), 3.0), (t_in, 1.0)):
        out, g = texture_gain(compose, tex, target, max_gain=top)
        assert g == 1.0 and np.array_equal(out, compose(1.0))
    # out of reach: the cap, and the output at the cap
    out, g = texture_gain(compose, tex, 10 * t_in, max_gain=1.25)
    assert g == 1.25 and np.array_equal(out, compose(1.25))
