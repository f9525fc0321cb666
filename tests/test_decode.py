"""Scaffold-GS neural-Gaussian decode (coin_cl.engine.ops.decode, kernels/decode.cl) against its
float64 torch twin (coin_cl.engine.reference.decode_neural_gaussians): values, gradients for random
cotangents, every output written, stiff inputs."""

import pytest
import torch
from conftest import small_mode

from coin_cl.engine import ops, reference

pytestmark = pytest.mark.kernel

SMALL = small_mode()
A, K = (40, 4) if SMALL else (3000, 10)
NAMES = ("means", "quats", "scales", "opacities", "colors")


@pytest.fixture
def rt(poisoned_rt):
    return poisoned_rt  # every output starts as NaN: an unwritten element shows


def _inputs(seed: int, frac_visible: float = 0.6, stiff: bool = False):
    g = torch.Generator().manual_seed(seed)
    anchors = torch.randn(A, 3, generator=g, dtype=torch.float64) * 3
    offsets = torch.randn(A, K, 3, generator=g, dtype=torch.float64)
    scaling = torch.randn(A, 6, generator=g, dtype=torch.float64) * 0.5 - 2
    vidx = torch.randperm(A, generator=g)[: int(frac_visible * A)].sort().values
    V = vidx.numel()
    opacity = torch.tanh(torch.randn(V * K, generator=g, dtype=torch.float64))
    cov = torch.randn(V * K, 7, generator=g, dtype=torch.float64)
    color = torch.rand(V * K, 3, generator=g, dtype=torch.float64)
    if stiff and V:
        cov[0, 3:] = 0.0  # zero quaternion: the norm clamp holds
        cov[1, 3:] = 1e-20  # below the clamp
        cov[2, :3] = torch.tensor([80.0, -80.0, 0.0])  # saturated sigmoids
        cov[3, 3:] = torch.tensor([1e18, -1e18, 1e18, 1.0])  # huge quaternion
        scaling[vidx[0], :] = -30.0  # vanishing scales (exp underflows toward 0)
        opacity[:K] = torch.tensor([0.0, 1.0, -1.0, 1e-7] * (K // 4) + [0.5] * (K % 4))
    sidx = (opacity > 0).nonzero().squeeze(1)
    # The kernels see float32 inputs: hand the twin those values in float64.
    f = [t.float().double() for t in (anchors, offsets, scaling, opacity, cov, color)]
    return (*f, vidx, sidx)


def _run(fn, inputs, cot=None):
    anchors, offsets, scaling, opacity, cov, color, vidx, sidx = inputs
    leaves = [t.clone().requires_grad_() for t in (offsets, scaling, opacity, cov, color)]
    out = fn(anchors, *leaves, vidx, sidx)
    if cot is None:
        g = torch.Generator().manual_seed(7)
        cot = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in out]
    s = sum((o.double() * c).sum() for o, c in zip(out, cot, strict=True))
    grads = torch.autograd.grad(s, leaves, allow_unused=True) if s.requires_grad else [None] * 5
    return [o.detach().double() for o in out], grads, cot


@pytest.mark.parametrize("seed", [0, 1])
def test_decode_forward_and_gradients_match_the_twin(rt, seed):
    inputs = _inputs(seed)
    ref, rgrads, cot = _run(reference.decode_neural_gaussians, inputs)
    got, ggrads, _ = _run(lambda *a: ops.decode_neural_gaussians(*a, device=rt), inputs, cot)
    assert ref[0].shape[0] == inputs[-1].numel() > 0
    for name, a, e in zip(NAMES, got, ref, strict=True):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, e, rtol=2e-6, atol=2e-6, msg=name)
    for name, a, e in zip(("offsets", "scaling", "opacity", "cov", "color"), ggrads, rgrads, strict=True):
        assert a is not None and torch.isfinite(a).all(), name
        torch.testing.assert_close(a.double(), e, rtol=1e-5, atol=1e-5, msg=name)
    # Anchors outside the frustum get exactly zero gradient.
    hidden = torch.ones(A, dtype=torch.bool)
    hidden[inputs[6]] = False
    assert ggrads[0][hidden].abs().max() == 0 and ggrads[1][hidden].abs().max() == 0


def test_decode_stiff_inputs_are_finite_and_match_the_twin(rt):
    inputs = _inputs(2, stiff=True)
    ref, rgrads, cot = _run(reference.decode_neural_gaussians, inputs)
    got, ggrads, _ = _run(lambda *a: ops.decode_neural_gaussians(*a, device=rt), inputs, cot)
    for name, a, e in zip(NAMES, got, ref, strict=True):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, e, rtol=2e-6, atol=2e-6, msg=name)
    # The zero quaternion decodes to zero (the rasterizer culls it); gradients are finite, and the
    # clamp's gradient (1 / 1e-12 per unit cotangent) matches the twin's.
    for name, a, e in zip(("offsets", "scaling", "opacity", "cov", "color"), ggrads, rgrads, strict=True):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a.double(), e, rtol=1e-5, atol=1e-5 * e.abs().max().item(), msg=name)


@pytest.mark.parametrize("frac", [0.0, 1.0])
def test_decode_with_no_or_every_anchor_visible(rt, frac):
    inputs = _inputs(3, frac_visible=frac)
    got, ggrads, cot = _run(lambda *a: ops.decode_neural_gaussians(*a, device=rt), inputs)
    ref, rgrads, _ = _run(reference.decode_neural_gaussians, inputs, cot)
    for a, e in zip(got, ref, strict=True):
        assert a.shape == e.shape
        torch.testing.assert_close(a, e, rtol=2e-6, atol=2e-6)
    if frac == 0.0:
        assert got[0].shape == (0, 3)
    else:
        for a, e in zip(ggrads, rgrads, strict=True):
            torch.testing.assert_close(a.double(), e, rtol=1e-5, atol=1e-5)


def test_no_drawn_offset_gives_empty_outputs_and_zero_gradients(rt):
    anchors, offsets, scaling, opacity, cov, color, vidx, _ = _inputs(4)
    sidx = torch.zeros(0, dtype=torch.long)
    out = ops.decode_neural_gaussians(anchors, offsets, scaling, opacity, cov, color, vidx, sidx, device=rt)
    assert all(o.shape[0] == 0 for o in out)
