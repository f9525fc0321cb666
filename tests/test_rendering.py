"""The public `rasterize` on stiff and extreme inputs: each case gives a clear error or a finite,
documented result (never a crash, a hang or a silent NaN), and the twin agrees where it applies."""

import math

import pytest
import torch
from conftest import small_mode

from coin_cl import PairOverflowError
from coin_cl.engine.rendering import rasterize
from coin_cl.testing import Gaussians, look_at_camera, random_gaussians

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel

SMALL = small_mode()
W, H = (32, 24) if SMALL else (96, 64)


def render(gs: Gaussians, viewmat=None, K=None, width=W, height=H, backend="opencl", **kw):
    if viewmat is None:
        viewmat, K = look_at_camera(width, height)
    return rasterize(*gs.tensors(), viewmat, K, width, height, backend=backend, **kw)


def both(gs: Gaussians, **kw):
    """Render with the kernels and the float64 twin; check they agree and are finite."""
    out = render(gs, **kw)
    ref = render(gs.to(torch.float64), backend="torch", **kw)
    for a, b in zip(out[:2], ref[:2]):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a.double(), b, rtol=1e-5, atol=5e-6)
    return out


def finite_grads(gs: Gaussians, **kw):
    gs.requires_grad_()
    img, alpha, _, _ = render(gs, **kw)
    (img.square().sum() + alpha.sum()).backward()
    for t in gs.tensors():
        assert t.grad is not None and torch.isfinite(t.grad).all()


def one(mean=(0.0, 0.0, 4.0), scale=0.1, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), n=1):
    t = lambda v, shape: torch.tensor(v, dtype=torch.float32).expand(*shape).clone()  # noqa: E731
    return Gaussians(
        t(mean, (n, 3)), t(quat, (n, 4)), t(scale, (n, 3)), t(opacity, (n,)), t((0.2, 0.5, 0.9), (n, 3))
    )


@pytest.mark.parametrize("scale", [1e-8, 1e-3, 1.0, 1e3])
def test_tiny_and_huge_scales(scale):
    gs = one(scale=scale, opacity=0.9)
    img, alpha, _, meta = both(gs)
    if scale <= 1e-3:  # sub-pixel: the 0.3 px^2 low-pass keeps it a ~1 px splat, still drawn
        assert 0 < meta["radii"][0] <= 3 and alpha.max() > 0.2
    if scale >= 1e3:  # covers the screen: every pixel sees it, clamped to MAX_ALPHA at most
        assert alpha.min() > 0.5 and alpha.max() <= 0.99 + 1e-6
    finite_grads(gs)


def test_flat_gaussian_zero_axis():
    gs = one()
    gs.scales[0] = torch.tensor([0.3, 0.0, 0.2])
    img, alpha, _, meta = both(gs)
    assert meta["visible"].all() and alpha.max() > 0
    finite_grads(gs)


@pytest.mark.parametrize("opacity", [0.0, 1.0, 1 - 1e-7])
def test_opacity_extremes(opacity):
    gs = one(opacity=opacity, scale=1.0)  # wide enough that the centre pixels reach the clamp
    bg = torch.tensor([0.1, 0.2, 0.3])
    img, alpha, _, _ = both(gs, background=bg)
    if opacity == 0.0:  # invisible: culled from the bins, image is the background
        assert alpha.abs().max() == 0 and torch.allclose(img, bg.expand_as(img))
    else:  # alpha is clamped to MAX_ALPHA = 0.99 at the centre, and opacity gets no gradient there
        assert abs(alpha.max().item() - 0.99) < 1e-6
    gs.requires_grad_()
    img, alpha, _, _ = render(gs)
    alpha.sum().backward()
    assert torch.isfinite(gs.opacities.grad).all()


@pytest.mark.parametrize(
    "z, visible",
    [(-1.0, False), (0.0, False), (0.0099999, False), (0.0100001, True), (1e5, True), (2e10, False)],
)
def test_behind_on_and_beyond_the_clip_planes(z, visible):
    gs = one(mean=(0.0, 0.0, z), scale=1e-3)
    img, alpha, _, meta = both(gs)
    assert bool(meta["visible"][0]) == visible
    if not visible:
        assert alpha.abs().max() == 0
    finite_grads(gs)


def test_straddling_tile_and_image_borders():
    gs = random_gaussians(40, seed=2, scale_range=(0.05, 0.3), dtype=torch.float32)
    # means placed on tile borders (x = 16, 32 px) and on the image edges
    viewmat, K = look_at_camera(W, H)
    f, cx, cy = K[0, 0].item(), K[0, 2].item(), K[1, 2].item()
    px = torch.tensor([0.0, 16.0, 32.0, W, W - 0.5, 15.99, 16.01, -3.0] * 5)
    py = torch.tensor([0.0, 16.0, H, H - 0.5, 8.0, -2.0, 16.0, 31.99] * 5)
    z = gs.means[:, 2]
    gs.means[:, 0] = (px - cx) / f * z
    gs.means[:, 1] = (py - cy) / f * z
    both(gs, viewmat=viewmat, K=K)


def test_zero_and_one_gaussian():
    empty = Gaussians(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)
    )
    bg = torch.tensor([0.3, 0.6, 0.9])
    img, alpha, depth, meta = render(empty, background=bg, return_depth=True)
    assert torch.allclose(img, bg.expand(H, W, 3)) and alpha.abs().max() == 0
    assert depth.abs().max() == 0 and meta["n_pairs"] == 0
    single = one()
    both(single)


def test_one_by_one_image():
    gs = random_gaussians(30, seed=4, dtype=torch.float32)
    viewmat, K = look_at_camera(1, 1, fov_deg=90)
    img, alpha, _, _ = both(gs, viewmat=viewmat, K=K, width=1, height=1)
    assert img.shape == (1, 1, 3)


def test_non_square_off_centre_principal_point():
    gs = random_gaussians(200, seed=5, dtype=torch.float32)
    viewmat, K = look_at_camera(70, 33, cx=10.0, cy=30.0)
    both(gs, viewmat=viewmat, K=K, width=70, height=33)


def test_many_gaussians_stacked_on_one_tile():
    n = 2_000 if SMALL else 100_000
    g = torch.Generator().manual_seed(6)
    gs = one(scale=0.01, opacity=0.5, n=n)
    gs.means = gs.means + torch.randn(n, 3, generator=g) * torch.tensor([0.01, 0.01, 0.5])
    gs.opacities = torch.rand(n, generator=g) * 0.3
    img, alpha, _, meta = render(gs, width=16, height=16)
    assert meta["n_pairs"] >= n // 2 and torch.isfinite(img).all()
    # compositing stops before T < 1e-4, so alpha saturates at 1 - 1e-4 at most
    assert alpha.max() <= 1 - 1e-4 + 1e-6 and alpha.max() > 0.99
    if SMALL or n <= 100_000:
        sub = Gaussians(*(t[: n // 20] for t in gs.tensors()))
        both(sub, width=16, height=16)


def test_finite_rows_fast_path_never_hides_a_nonfinite_row_and_survives_overflow():
    from coin_cl.engine.geometry import finite_rows

    big = torch.full((4, 3), 3e38)  # every entry finite, but the sum overflows to inf
    assert finite_rows(big, torch.ones(4)).all()
    for bad in (float("nan"), float("inf"), -float("inf")):
        x = torch.zeros(6, 3)
        x[4, 1] = bad
        assert finite_rows(torch.ones(6, 2), x).tolist() == [True] * 4 + [False, True]
    assert finite_rows(torch.zeros(0, 3)).shape == (0,)


def test_nonfinite_inputs_are_culled_and_reported(caplog):
    gs = random_gaussians(50, seed=7, dtype=torch.float32)
    gs.means[0, 0] = float("nan")
    gs.quats[1, 2] = float("inf")
    gs.scales[2, 1] = -float("inf")
    gs.opacities[3] = float("nan")
    gs.colors[4, 0] = float("inf")
    gs.quats[5] = 0.0  # zero quaternion: no rotation defined
    img, alpha, _, meta = render(gs)
    assert meta["n_nonfinite"] == 5
    assert "culled 5 Gaussians with NaN/Inf" in caplog.text
    assert not meta["visible"][:6].any()
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    clean = Gaussians(*(t[6:] for t in gs.tensors()))
    torch.testing.assert_close(img, render(clean)[0], rtol=1e-6, atol=1e-7)
    gs.requires_grad_()
    out = render(gs)
    (out[0].sum() + out[1].sum()).backward()
    for t in gs.tensors():
        assert torch.isfinite(t.grad).all() and (t.grad[:6] == 0).all()


def test_screen_filling_splats_hit_the_pair_cap():
    gs = one(scale=50.0, n=100)
    with pytest.raises(PairOverflowError, match="max_pairs=99"):
        render(gs, max_pairs=99)
    with pytest.raises(PairOverflowError):
        render(gs.to(torch.float64), backend="torch", max_pairs=99)
    img, alpha, _, meta = render(gs)  # under the default cap it renders, finite
    tiles = math.ceil(W / 16) * math.ceil(H / 16)
    assert meta["n_pairs"] == 100 * tiles and torch.isfinite(img).all()


@pytest.mark.parametrize("s", [1e-4, 1e4])
def test_tiny_and_huge_scenes_render_alike(s):
    """Scaling the whole world (scene, camera, near plane) leaves the image unchanged."""
    gs = random_gaussians(150, seed=8, dtype=torch.float64)
    viewmat, K = look_at_camera(W, H, eye=(0.2, -0.1, -0.5))
    base = render(gs.to(torch.float32), viewmat=viewmat.float(), K=K.float())[0]
    big = Gaussians(gs.means * s, gs.quats, gs.scales * s, gs.opacities, gs.colors)
    vm = viewmat.clone()
    vm[:3, 3] *= s
    scaled = render(big.to(torch.float32), viewmat=vm.float(), K=K.float(), near=0.01 * s)[0]
    torch.testing.assert_close(scaled, base, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"viewmat": torch.full((4, 4), float("nan"))}, "viewmat has non-finite"),
        ({"K": torch.zeros(3, 3)}, "non-positive focal"),
        ({"means": torch.zeros(5, 2)}, "means has shape"),
        ({"colors": torch.zeros(3, 200)}, "colors has shape"),
        ({"width": 0}, "at least 1x1"),
    ],
)
def test_bad_arguments_raise_clear_errors(bad, match):
    gs = random_gaussians(3, seed=9, dtype=torch.float32)
    viewmat, K = look_at_camera(W, H, dtype=torch.float32)
    args = dict(zip(["means", "quats", "scales", "opacities", "colors"], gs.tensors()))
    args.update(viewmat=viewmat, K=K, width=W, height=H)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        rasterize(**args)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_background_is_a_clear_value_error(value):
    """A NaN or Inf background would fill every uncovered pixel: refused before any work, naming
    the argument (a ValueError, the engine's NonFiniteInputError)."""
    from coin_cl.engine.errors import NonFiniteInputError

    with pytest.raises(NonFiniteInputError, match=r"background is \[0.0, .*must be finite") as e:
        render(one(), background=torch.tensor([0.0, value, 1.0]), backend="torch")
    assert isinstance(e.value, ValueError)
