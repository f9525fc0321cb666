"""Per-surface harmonic chroma under FSR (`coin_cl.diffusion.surface_chroma`): known answers."""

import cv2
import numpy as np
import pytest
from coin_cl.diffusion.exemplar import ExemplarConfig, exemplar_inpaint, smooth_fill
from coin_cl.diffusion.surface_chroma import SurfaceChromaConfig, ring_clusters, surface_chroma, two_means

WOOD = np.array([0.75, 0.5, 0.25], np.float32)
WALL = np.array([0.62, 0.64, 0.7], np.float32)


def _two_surfaces(H=90, W=120, edge=60, noise=0.005):
    """Wood left of column `edge`, wall right of it, with a little sensor noise."""
    rng = np.random.default_rng(0)
    img = np.where(np.arange(W)[None, :, None] < edge, WOOD, WALL) * np.ones((H, 1, 1), np.float32)
    return np.clip(img + noise * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def _chroma(rgb):
    return cv2.cvtColor(np.asarray(rgb, np.float32), cv2.COLOR_RGB2YCrCb)[..., 1:]


def test_each_side_of_an_edge_through_the_hole_keeps_its_own_colour():
    # FSR's answer given as the truth's edge under tints of the other side's colour on both sides:
    # each side returns to its own colour and the edge stays where FSR drew it; a harmonic chroma
    # would grey the two together
    img = _two_surfaces()
    hole = np.zeros(img.shape[:2], bool)
    hole[20:70, 30:90] = True
    truth = _two_surfaces(noise=0.0)
    fsr = truth.copy()
    fsr[30:40, 40:50] = 0.7 * WOOD + 0.3 * WALL
    fsr[50:60, 66:80] = 0.7 * WALL + 0.3 * WOOD
    out = surface_chroma(img, hole, fsr)
    err = np.abs(_chroma(out) - _chroma(truth)).sum(-1)[hole]
    harmonic = np.abs(_chroma(smooth_fill(img, hole, "harmonic")) - _chroma(truth)).sum(-1)[hole]
    assert err.mean() < 0.004 and harmonic.mean() > 5 * err.mean()
    mid = (_chroma(WOOD[None, None])[0, 0, 0] + _chroma(WALL[None, None])[0, 0, 0]) / 2
    crossing = 30 + np.argmax(_chroma(out)[20:70, 30:90, 0] < mid, axis=1)  # wood has the higher Cr
    assert np.abs(crossing - 60).max() <= 1


def test_a_tint_inside_one_surface_is_taken_out_and_luminance_kept():
    # FSR's fill given with a green blob far inside a plain wood hole: the chroma returns to the
    # wood's, the luminance is FSR's
    img = _two_surfaces(edge=200)
    hole = np.zeros(img.shape[:2], bool)
    hole[20:70, 30:90] = True
    fsr = img.copy()
    fsr[hole] = WOOD
    fsr[35:55, 50:70] = [0.55, 0.65, 0.35]
    out = surface_chroma(img, hole, fsr)
    assert np.abs(_chroma(out) - _chroma(WOOD[None, None]))[hole].max() < 0.01
    y_in = cv2.cvtColor(fsr, cv2.COLOR_RGB2YCrCb)[..., 0]
    y_out = cv2.cvtColor(out, cv2.COLOR_RGB2YCrCb)[..., 0]
    assert np.abs(y_out - y_in)[hole].max() < 0.02  # up to the clip back into [0, 1]


def test_pixels_outside_the_hole_are_the_image_and_edge_cases_are_finite():
    img = _two_surfaces()
    hole = np.zeros(img.shape[:2], bool)
    hole[:25, :40] = True  # touches two image borders
    hole[60:80, 100:] = True  # a second part, on the right border
    out = surface_chroma(img, hole, smooth_fill(img, hole, "fsr_fast"))
    assert np.array_equal(out[~hole], img[~hole])
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    assert np.array_equal(surface_chroma(img, np.zeros_like(hole), img), img)  # empty hole
    full = np.ones_like(hole)  # no ring: FSR's own answer, untouched
    assert np.array_equal(surface_chroma(img, full, img), img)
    bad = img.copy()
    bad[0, 0, 1] = np.nan
    with pytest.raises(ValueError, match="NaN/Inf"):
        surface_chroma(bad, hole, img)
    with pytest.raises(ValueError, match="NaN/Inf"):
        surface_chroma(img, hole, bad)


def test_one_cluster_when_the_ring_is_one_colour_or_the_second_is_too_small():
    def clusters(x):
        return len(ring_clusters(x.reshape(500, 1, 3), np.ones((500, 1), bool), SurfaceChromaConfig()))

    rng = np.random.default_rng(1)
    one = 0.5 + 0.003 * rng.standard_normal((500, 3))
    two = one.copy()
    two[:200] += 0.08
    few = one.copy()
    few[:30] += 0.08  # 6 % of the ring: a patch of another colour, not a surface
    assert (clusters(one), clusters(two), clusters(few)) == (1, 2, 1)
    centres, labels = two_means(two)
    assert sorted(np.bincount(labels).tolist()) == [200, 300]
    assert abs(np.linalg.norm(centres[0] - centres[1]) - 0.08 * np.sqrt(3)) < 0.01


def test_the_exemplar_inpainter_takes_the_structure_by_name():
    # with the plain-surroundings rule covering every ring the exemplar returns its structure fill
    # alone: for "fsr_surfaces" that is FSR under the per-surface chroma, not FSR itself
    img = _two_surfaces(noise=0.03)
    hole = np.zeros(img.shape[:2], bool)
    hole[30:60, 45:75] = True
    out = exemplar_inpaint(img, hole, ExemplarConfig(structure="fsr_surfaces", plain_rms=1.0))
    want = surface_chroma(img, hole, smooth_fill(img, hole, "fsr_fast"))
    np.testing.assert_array_equal(out, want)
    assert not np.array_equal(out, exemplar_inpaint(img, hole, ExemplarConfig(plain_rms=1.0)))
