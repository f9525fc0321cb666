"""The grain transport (coin_cl.diffusion.directional) on holes with a known answer: slanted lines it
must continue with their phase, one thin line, surroundings with no orientation, another object
beside the hole, holes at the image border, and its refusals."""

import math

import numpy as np
import pytest
from coin_cl.diffusion.directional import DirectionalConfig, directional_band, known_band, ring_orientation


def _lines(H=80, W=96, angle_deg=60.0, period=5.0, amp=0.08, base=(0.62, 0.48, 0.30), seed=None):
    """Wood-like grain: thin lines along `angle_deg` (image x right, y down), periodic or (with a
    seed) at random spacing and strength, so no shifted copy of the surroundings matches the hole;
    returns image, the unit direction along the lines."""
    a = math.radians(angle_deg)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    across = -x * math.sin(a) + y * math.cos(a)  # coordinate across the lines
    if seed is None:
        wave = amp * np.sin(2 * np.pi * across / period)
    else:  # a random profile across the lines, smoothed over about a line's width
        grid = np.arange(np.floor(across.min()) - 4, np.ceil(across.max()) + 5)
        prof = np.random.default_rng(seed).standard_normal(len(grid))
        prof = np.convolve(prof, np.ones(2) / 2, mode="same")
        wave = amp * np.interp(across, grid, prof / prof.std())
    img = np.asarray(base, np.float32) + wave[..., None] * np.array([1.0, 0.9, 0.7], np.float32)
    return img.astype(np.float32), (math.cos(a), math.sin(a))


def _square(H=80, W=96, y0=28, x0=36, side=24):
    m = np.zeros((H, W), bool)
    m[y0 : y0 + side, x0 : x0 + side] = True
    return m


def _truth_band(img, hole, sigma=2.0):
    return known_band(img, np.ones_like(hole), sigma)


@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0, 90.0, 135.0])
def test_slanted_lines_continue_with_their_phase(angle):
    img, along = _lines(angle_deg=angle)
    hole = _square()
    band, oriented, orients = directional_band(img, hole)
    assert len(orients) == 1 and orients[0].coherence > 0.9
    assert abs(along[0] * orients[0].direction[0] + along[1] * orients[0].direction[1]) > 0.99
    assert oriented[hole].all() and not oriented[~hole].any()
    assert not band[~hole].any()  # nothing written outside the hole
    truth = _truth_band(img, hole)[hole]
    got = band[hole]
    corr = float((got * truth).sum() / math.sqrt((got**2).sum() * (truth**2).sum()))
    assert corr > 0.9, corr  # in phase: a patch copy at a random offset scores about 0
    assert 0.7 < np.sqrt((got**2).mean() / (truth**2).mean()) < 1.2  # the lines' strength, not faded


def test_a_thin_line_leaves_the_hole_where_it_entered_it():
    img = np.full((64, 64, 3), 0.7, np.float32)
    img[:, 30:32] = 0.2  # one dark vertical line, 2 px wide
    hole = _square(64, 64, 20, 20, 24)
    band, _, orients = directional_band(img, hole)
    assert orients[0].coherence > 0.9
    rows = band[22:42, :, 0]  # the hole's middle rows: darkest where the line continues
    assert np.all(np.abs(rows.argmin(1) - 30.5) <= 1.5)
    assert np.all(band[22:42, 20:27].max() < 0.02)  # and nothing of it beside the line


def test_isotropic_surroundings_transport_nothing():
    rng = np.random.default_rng(0)
    noise = 0.5 + 0.1 * rng.standard_normal((72, 72, 3)).astype(np.float32)
    y, x = np.mgrid[0:72, 0:72]
    tiles = np.full((72, 72, 3), 0.8, np.float32)
    tiles[(y % 12 < 2) | (x % 12 < 2)] = 0.4  # joints in two directions: no one orientation
    for img in (noise.clip(0, 1), tiles):
        hole = _square(72, 72, 24, 24, 24)
        band, oriented, orients = directional_band(img, hole)
        assert orients[0].coherence < DirectionalConfig().min_coherence, orients[0].coherence
        assert not oriented.any() and not band.any()


def test_another_object_beside_the_hole_is_not_carried_into_it():
    img, _ = _lines(angle_deg=90.0)  # vertical grain
    hole = _square()  # rows 28-51, columns 36-59
    img[10:28, 40:56] = (0.97, 0.97, 0.95)  # a white object touching the hole's top side
    band, _, orients = directional_band(img, hole)
    assert orients[0].coherence > 0.8
    clean, _ = _lines(angle_deg=90.0)
    ref, _, _ = directional_band(clean, hole)
    # the lines that meet the object above take the grain below alone: the clean fill, to within
    # the one-sided average's difference
    under = np.zeros_like(hole)
    under[28:52, 43:53] = True  # columns whose upward line meets the object (off its edge's blur)
    np.testing.assert_allclose(band[under], ref[under], atol=0.03)


def test_holes_at_the_border_and_lines_that_leave_the_image():
    img, _ = _lines(angle_deg=90.0)
    top = np.zeros(img.shape[:2], bool)
    top[:20, 30:60] = True  # touches the top border: every vertical line meets wood below only
    band, oriented, _ = directional_band(img, top)
    assert oriented[top].all() and np.isfinite(band).all()
    truth = _truth_band(img, top)[top]
    corr = float((band[top] * truth).sum() / math.sqrt((band[top] ** 2).sum() * (truth**2).sum()))
    assert corr > 0.9
    full_height = np.zeros(img.shape[:2], bool)
    full_height[:, 40:50] = True  # vertical lines inside it meet no known pixel on either side
    band, _, _ = directional_band(img, full_height)
    assert not band[full_height].any()


def test_empty_hole_and_bad_input():
    img, _ = _lines()
    band, oriented, orients = directional_band(img, np.zeros(img.shape[:2], bool))
    assert not band.any() and not oriented.any() and orients == []
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        directional_band(bad, _square())


def test_a_ring_too_thin_to_judge_has_no_orientation():
    img, _ = _lines(H=40, W=40)
    hole = np.ones((40, 40), bool)
    hole[:, 38:] = False  # two known columns, all within the guard and the tensor's reach
    assert ring_orientation(img, hole, hole, DirectionalConfig()) is None


@pytest.mark.parametrize("bad", [{"min_coherence": 1.5}, {"sigma": 0.0}, {"rho": math.inf},
                                 {"samples": 0}, {"guard_px": 0.5}, {"mismatch": -1.0}])  # fmt: skip
def test_config_refuses_bad_values(bad):
    with pytest.raises(ValueError, match=f"DirectionalConfig.{next(iter(bad))}"):
        DirectionalConfig(**bad)
