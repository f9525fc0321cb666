"""Gradient-domain blending (`coin_cl.diffusion.poisson`): known answers of the Poisson equation."""

import numpy as np
import pytest
from coin_cl.diffusion.poisson import poisson_blend


def _ramp(H=40, W=50):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([0.2 + 0.006 * xx, 0.3 + 0.005 * yy, 0.4 + 0.003 * (xx + yy)], -1)


def test_texture_on_a_shifted_source_keeps_the_texture_and_takes_the_surroundings_colour():
    # the guide is the base plus a constant offset (another exposure) plus texture; with the
    # guide's region labelled apart, the offset is not carried across the edge: the answer is the
    # base (a linear ramp is harmonic) plus the texture, up to the texture's own edge pixels
    rng = np.random.default_rng(0)
    base = _ramp()
    region = np.zeros(base.shape[:2], bool)
    region[10:30, 12:40] = True
    tex = np.zeros_like(base)
    tex[12:28, 14:38] = 0.05 * rng.standard_normal((16, 24, 3))
    guide = base + 0.3 + tex
    out = poisson_blend(base, guide, region, region.astype(int))
    assert np.abs(out - (base + tex))[region].mean() < 0.004  # the offset 0.3 is gone
    assert np.array_equal(out[~region], base[~region].astype(np.float32))


def test_one_label_keeps_the_guide_as_is():
    # classic Poisson editing with the guide equal to the base outside: the guide itself solves it
    base = _ramp()
    region = np.zeros(base.shape[:2], bool)
    region[5:25, 5:25] = True
    guide = base.copy()
    guide[region] += 0.2
    out = poisson_blend(base, guide, region)
    np.testing.assert_allclose(out[region], np.clip(guide[region], 0, 1), atol=1e-5)


def test_a_region_on_the_border_is_continued_not_pinned():
    # a hole in the corner: its outside neighbours are on two sides only; a constant-colour
    # surrounding and a flat guide give that colour everywhere (never 0 or an invented value)
    base = np.full((30, 30, 3), 0.6)
    region = np.zeros((30, 30), bool)
    region[:12, :15] = True
    guide = np.full_like(base, 0.1)
    out = poisson_blend(base, guide, region, region.astype(int))
    np.testing.assert_allclose(out, 0.6, atol=1e-4)


def test_full_and_empty_regions():
    rng = np.random.default_rng(1)
    base = rng.random((16, 20, 3))
    guide = rng.random((16, 20, 3))
    # no pixel outside: the screened system returns the guide (documented)
    out = poisson_blend(base, guide, np.ones((16, 20), bool))
    np.testing.assert_allclose(out, guide, atol=1e-4)
    out = poisson_blend(base, guide, np.zeros((16, 20), bool))
    assert np.array_equal(out, base.astype(np.float32))


def test_bad_input_is_an_error_naming_it():
    base = np.zeros((8, 8, 3))
    region = np.zeros((8, 8), bool)
    region[2:5, 2:5] = True
    guide = base.copy()
    guide[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="guide is not finite"):
        poisson_blend(base, guide, region)
    with pytest.raises(ValueError, match="must be"):
        poisson_blend(base, np.zeros((8, 9, 3)), region)
    bad = base.copy()
    bad[1, 3] = np.inf  # on the region's boundary
    with pytest.raises(ValueError, match="base is not finite"):
        poisson_blend(bad, np.zeros((8, 8, 3)), region)
