"""Per-pixel SSIM (coin_cl.engine.ops.ssim, kernels/ssim.cl) against its float64 torch twin
(coin_cl.engine.reference.ssim_map): values, gradients for random cotangents, every output written,
stiff inputs; and the photometric loss on both paths."""

import math

import pytest
import torch
from conftest import small_mode

from coin_cl.engine import ops, reference
from coin_cl.gs.losses import LossConfig, photometric_loss

pytestmark = pytest.mark.kernel

SMALL = small_mode()
B, H, W = (1, 9, 14) if SMALL else (2, 37, 53)  # not multiples of anything on purpose


@pytest.fixture
def rt(poisoned_rt):
    return poisoned_rt  # every output starts as NaN: an unwritten element shows


def _images(seed: int, c: int = 3, shape=(B, H, W)):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(*shape, c, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(*shape, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    return a, b


def _both(a, b, rt, v=None, **kw):
    """(op value, twin value, op grad, twin grad) for cotangent v (random when None)."""
    x = a.float().requires_grad_()
    got = ops.ssim_map(x, b.float(), device=rt, **kw)
    xd = a.clone().requires_grad_()
    want = reference.ssim_map(xd, b, **kw)
    if v is None:
        v = torch.randn(want.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    (gx,) = torch.autograd.grad(got, x, v.float())
    (gd,) = torch.autograd.grad(want, xd, v)
    return got, want, gx, gd


@pytest.mark.parametrize("channels, window", [(3, 11), (1, 11), (3, 5)])
def test_values_and_gradients_match_the_twin(rt, channels, window):
    a, b = _images(0, channels)
    got, want, gx, gd = _both(a, b, rt, window=window, sigma=1.5 if window == 11 else 0.8)
    assert got.shape == (B, H, W) and gx.shape == a.shape
    assert torch.isfinite(got).all() and torch.isfinite(gx).all(), "an output was left unwritten"
    assert (got.double() - want).abs().max() < 2e-5
    scale = gd.abs().max()
    assert (gx.double() - gd).abs().max() / scale < 1e-4


def test_identical_images_give_one_and_no_gradient_at_the_optimum(rt):
    a, _ = _images(1)
    got, want, gx, gd = _both(a, a, rt, v=torch.ones(B, H, W, dtype=torch.float64))
    assert torch.allclose(got.double(), torch.ones_like(want), atol=1e-5)
    assert gx.abs().max() < 1e-3 and gd.abs().max() < 1e-9  # SSIM is maximal: the gradient vanishes


@pytest.mark.parametrize(
    "what",
    ["constant equal", "constant different", "zeros and ones", "one pixel", "smaller than window"],
)
def test_stiff_inputs_are_finite_and_match_the_twin(rt, what):
    """Flat windows (zero variance: c1, c2 keep S finite), saturated values, images of one pixel or
    narrower than the window (zero padding everywhere)."""
    a, b = _images(2)
    if what == "constant equal":
        a, b = torch.full_like(a, 0.3), torch.full_like(b, 0.3)
    elif what == "constant different":
        a, b = torch.full_like(a, 0.0), torch.full_like(b, 1.0)
    elif what == "zeros and ones":
        a, b = (a > 0.5).double(), (b > 0.5).double()
    elif what == "one pixel":
        a, b = _images(3, shape=(1, 1, 1))
    else:
        a, b = _images(4, shape=(2, 3, 5))
    got, want, gx, gd = _both(a, b, rt)
    assert torch.isfinite(got).all() and torch.isfinite(gx).all()
    assert (got.double() - want).abs().max() < 2e-5
    assert (gx.double() - gd).abs().max() <= 1e-4 * max(1.0, float(gd.abs().max()))


def test_empty_batch(rt):
    a = torch.zeros(0, H, W, 3)
    x = a.clone().requires_grad_()
    out = ops.ssim_map(x, a, device=rt)
    assert out.shape == (0, H, W)
    (g,) = torch.autograd.grad(out.sum(), x)
    assert g.shape == a.shape


@pytest.mark.parametrize(
    "where, value", [((15, 15), float("nan")), ((0, 29), float("inf")), ((29, 0), float("nan"))]
)
def test_nan_and_inf_spread_to_their_windows_only_as_in_the_twin(rt, where, value):
    """A NaN/Inf pixel (inside or on the edge) makes the SSIM of the windows it touches NaN
    (documented: the training loss then turns non-finite and the trainer stops naming the step);
    pixels farther away stay finite, in the op exactly where in the twin."""
    a, b = _images(5, shape=(1, 30, 30))
    a[0, where[0], where[1], 1] = value
    got = ops.ssim_map(a.float(), b.float(), device=rt)
    want = reference.ssim_map(a, b)
    assert torch.equal(torch.isfinite(got), torch.isfinite(want))
    assert not torch.isfinite(got[0, where[0], where[1]])
    assert torch.isfinite(got).sum() > 0.5 * got.numel()


def test_bad_input_is_a_clear_error(rt):
    a, b = _images(6)
    with pytest.raises(ValueError, match="one shape"):
        ops.ssim_map(a.float(), b.float()[:, :-1], device=rt)
    with pytest.raises(ValueError, match="odd width"):
        ops.ssim_map(a.float(), b.float(), window=10, device=rt)
    with pytest.raises(ValueError, match="first image only"):
        ops.ssim_map(a.float(), b.float().requires_grad_(), device=rt)
    with pytest.raises(ValueError, match="channels"):
        ops.ssim_map(torch.rand(1, 4, 4, 17), torch.rand(1, 4, 4, 17), device=rt)


@pytest.mark.parametrize("mask", ["none", "some", "all"])
def test_photometric_loss_is_the_same_on_both_paths(rt, mask):
    """The training loss with the kernel (fused path) equals the torch path: value and gradient,
    with exclusion masks (all excluded: loss 0, gradient exactly 0) and per-view weights."""
    a, b = _images(8)
    ex = None
    if mask != "none":
        ex = torch.zeros(B, H, W, dtype=torch.bool)
        ex[..., 2:7, 3:11] = True
        if mask == "all":
            ex[:] = True
    w = torch.tensor([1.0, 0.5][:B], dtype=torch.float32)
    res = []
    for backend in ("torch", "opencl"):
        x = a.float().requires_grad_()
        loss, parts = photometric_loss(x, b.float(), w, ex, LossConfig(), backend=backend, device=rt)
        (g,) = torch.autograd.grad(loss, x)
        res.append((loss, parts, g))
    (l_t, p_t, g_t), (l_o, p_o, g_o) = res
    assert math.isclose(float(l_o.detach()), float(l_t.detach()), rel_tol=1e-5, abs_tol=1e-7)
    assert torch.allclose(p_o["ssim"], p_t["ssim"], atol=1e-5)
    assert (g_o - g_t).abs().max() <= 1e-4 * max(float(g_t.abs().max()), 1e-6)
    if mask != "none":
        assert (g_o[ex] == 0).all()
    if mask == "all":
        assert float(l_o.detach()) == 0.0 and (g_o == 0).all()
