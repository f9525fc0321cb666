"""coin_cl.pipeline.observed_warp: a mask pixel's colour from the view that observes its surface."""

import numpy as np
import pytest

from coin_cl.pipeline.observed_warp import warp_observed
from coin_cl.scene.types import Camera
from coin_cl.testing import look_at_camera

W, H, Z = 48, 36, 5.0


def cam(x: float) -> Camera:
    viewmat, K = look_at_camera(W, H, fov_deg=50.0, eye=(x, 0.0, 0.0))
    return Camera(K=K.numpy(), viewmat=viewmat.numpy(), width=W, height=H)


def texture(X: np.ndarray) -> np.ndarray:
    """A smooth colour on the plane z = Z, so bilinear sampling is nearly exact."""
    r, g = 0.5 + 0.4 * np.sin(1.5 * X[:, 0]), 0.5 + 0.4 * np.cos(2.0 * X[:, 1])
    return np.stack([r, g, np.full_like(r, 0.5)], 1)


def capture(c: Camera) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W]
    X = c.unproject(np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1), np.full(H * W, Z))
    return texture(X).reshape(H, W, 3).astype(np.float32)


@pytest.fixture
def setup():
    n, m = cam(0.0), cam(0.4)
    pixels = np.zeros((H, W), bool)
    pixels[10:26, 14:34] = True
    return n, m, pixels


def test_observed_pixels_take_the_surface_colour_the_other_view_captured(setup):
    n, m, pixels = setup
    col, found, src = warp_observed({1: m}, {1: capture(m)}, {1: np.zeros((H, W), bool)}, np.full((H, W), Z),
                                    {1: np.full((H, W), Z)}, n, pixels, 0.03)  # fmt: skip
    assert found.sum() == pixels.sum() and not (found & ~pixels).any()
    assert (src[found] == 1).all() and (src[~found] == -1).all()
    truth = capture(n)
    assert np.abs(col[found] - truth[found]).max() < 0.02  # bilinear error of a smooth texture
    assert (col[~found] == 0).all()


def test_occluded_masked_or_far_off_surfaces_are_not_observed(setup):
    n, m, pixels = setup
    dm = np.full((H, W), Z)
    dm[:, : W // 2] = 3.0  # something in front of the plane in m's left half
    mask_m = np.zeros((H, W), bool)
    mask_m[:, W // 2 + 8 :] = True  # the object's mask covers m's right part
    _, found, _ = warp_observed(
        {1: m}, {1: capture(m)}, {1: mask_m}, np.full((H, W), Z), {1: dm}, n, pixels, 0.03
    )
    X = n.unproject(np.stack(np.nonzero(pixels)[::-1], 1) + 0.5, np.full(pixels.sum(), Z))
    px, _ = m.pixels(X)
    u = px[:, 0]
    # visible only in the band between the occluder and the (1 px grown) mask
    expect = (u >= W // 2) & (u < W // 2 + 8 - 1)
    assert found[pixels].tolist() == expect.tolist()
    # a depth hypothesis 10 % off: m's surface disagrees, nothing is observed
    off = np.full((H, W), 1.1 * Z)
    _, found, _ = warp_observed({1: m}, {1: capture(m)}, {1: np.zeros((H, W), bool)}, off,
                                {1: np.full((H, W), Z)}, n, pixels, 0.03)  # fmt: skip
    assert not found.any()


def test_the_view_closest_in_angle_gives_the_colour(setup):
    n, m, pixels = setup
    far = cam(1.5)
    imgs = {1: capture(m), 2: np.zeros((H, W, 3), np.float32)}
    none = {k: np.zeros((H, W), bool) for k in imgs}
    depth = {k: np.full((H, W), Z) for k in imgs}
    _, found, src = warp_observed({1: m, 2: far}, imgs, none, np.full((H, W), Z), depth, n, pixels, 0.03)
    assert found.any() and (src[found] == 1).all()


def test_empty_pixels_no_sources_no_surface_and_bad_tolerance(setup):
    n, m, pixels = setup
    args = ({1: m}, {1: capture(m)}, {1: np.zeros((H, W), bool)})
    col, found, src = warp_observed(*args, np.full((H, W), Z), {1: np.full((H, W), Z)}, n,
                                    np.zeros((H, W), bool), 0.03)  # fmt: skip
    assert not found.any() and (src == -1).all() and not col.any()
    _, found, _ = warp_observed({}, {}, {}, np.full((H, W), Z), {}, n, pixels, 0.03)
    assert not found.any()
    # no object-free surface (NaN, 0 or negative depth) and m capturing nothing (depth 0): no colour, no NaN
    d = np.full((H, W), np.nan)
    d[:, :10] = 0.0
    d[:, 10:20] = -1.0
    col, found, _ = warp_observed(*args, d, {1: np.full((H, W), Z)}, n, pixels, 0.03)
    assert not found.any() and np.isfinite(col).all()
    _, found, _ = warp_observed(*args, np.full((H, W), Z), {1: np.zeros((H, W))}, n, pixels, 0.03)
    assert not found.any()
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="tol"):
            warp_observed(*args, np.full((H, W), Z), {1: np.full((H, W), Z)}, n, pixels, bad)
