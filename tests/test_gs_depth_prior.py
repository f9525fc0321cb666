"""The reference depth loss and prior (coin_cl.gs.depth_prior): the affine fit, the loss, the
prior's sources and the depth inpainting."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from coin_cl.gs.depth_prior import (
    DATASET_DEPTH_PRIOR,
    GS_DEPTH_PRIOR,
    fit_affine,
    inpaint_depth,
    reference_depth_loss,
    reference_depth_prior,
)
from coin_cl.scene.types import Camera, Scene


@pytest.mark.parametrize("a,b", [(2.5, -0.7), (-3.0, 4.0), (0.01, 100.0)])
def test_fit_affine_recovers_scale_and_shift(a, b):
    g = torch.Generator().manual_seed(0)
    r = torch.rand(24, 32, generator=g, dtype=torch.float64) * 3 + 1
    d = a * r + b
    valid = torch.rand(24, 32, generator=g) > 0.3
    d_bad = torch.where(valid, d, torch.full_like(d, 1e4))  # outliers outside `valid` are ignored
    A, B = fit_affine(r, d_bad, valid)
    assert A == pytest.approx(a, rel=1e-6) and B == pytest.approx(b, rel=1e-6, abs=1e-6)


def test_fit_affine_degenerate_cases():
    r = torch.full((8, 8), 2.0)
    d = torch.arange(64.0).view(8, 8)
    A, B = fit_affine(r, d)
    assert (A, B) == (0.0, pytest.approx(31.5))
    with pytest.raises(ValueError, match="no valid"):
        fit_affine(r, d, torch.zeros(8, 8, dtype=torch.bool))
    # Non-finite pixels are skipped.
    r2 = torch.rand(8, 8) + 1
    d2 = 2 * r2 + 1
    r2[0, 0] = float("nan")
    d2[1, 1] = float("inf")
    assert fit_affine(r2, d2) == (pytest.approx(2.0), pytest.approx(1.0))


def test_reference_depth_loss_zero_on_affine_prior_and_gradient():
    g = torch.Generator().manual_seed(1)
    r = (torch.rand(16, 20, generator=g) * 2 + 1).requires_grad_(True)
    mask = np.zeros((16, 20), bool)
    mask[4:10, 5:12] = True
    prior = -1.7 * r.detach() + 6.0
    loss, info = reference_depth_loss(r, prior, mask, lambda_d=10.0)
    assert float(loss.detach()) == pytest.approx(0.0, abs=1e-5)
    assert info["A"] == pytest.approx(-1.7) and info["n_fit"] == 16 * 20 - 42
    # Prior differs inside the mask only: the fit (outside) is exact, the L1 runs over all pixels.
    prior2 = prior.clone()
    prior2[4:10, 5:12] += 0.5
    loss2, info2 = reference_depth_loss(r, prior2, mask, lambda_d=10.0)
    assert float(loss2.detach()) == pytest.approx(10.0 * 0.5 * 42 / 320, rel=1e-4)
    loss2.backward()
    # d/dR of lambda * mean |A R + B - D| = lambda * A * sign(...) / N; no gradient through A, B.
    gm = r.grad[4:10, 5:12]
    assert torch.allclose(gm, torch.full_like(gm, 10.0 * -1.7 * -1.0 / 320), rtol=1e-4)


def test_reference_depth_loss_disparity_constant_and_fallbacks(caplog):
    r = torch.rand(10, 12) * 4 + 1
    mask = np.zeros((10, 12), bool)
    mask[2:5, 3:7] = True
    loss, info = reference_depth_loss(r, 2.0 / r + 0.1, mask, disparity=True)
    assert float(loss) == pytest.approx(0.0, abs=1e-5) and info["A"] == pytest.approx(2.0, rel=1e-5)
    # Constant render depth: finite loss (the best constant fit) and a finite zero gradient.
    rc = torch.full((10, 12), 3.0, requires_grad=True)
    prior = torch.rand(10, 12)
    lc, ic = reference_depth_loss(rc, prior, mask)
    lc.backward()
    assert math.isfinite(float(lc.detach())) and ic["A"] == 0.0 and torch.isfinite(rc.grad).all()
    # Non-finite pixels and `valid`: left out of both the fit and the mean, zero gradient there.
    rn = r.clone()
    rn[0, 0] = float("nan")
    rn.requires_grad_(True)
    ln, _ = reference_depth_loss(rn, 2 * r + 1, mask, valid=torch.ones(10, 12, dtype=torch.bool))
    ln.backward()
    assert float(ln.detach()) == pytest.approx(0.0, abs=1e-5) and torch.isfinite(rn.grad).all()
    # A mask over the whole view: fit on the whole view, logged.
    with caplog.at_level(logging.WARNING, logger="coin_cl.gs.depth_prior"):
        lf, inf = reference_depth_loss(r, 3 * r, np.ones((10, 12), bool))
    assert float(lf) == pytest.approx(0.0, abs=1e-5) and inf["n_fit"] == 120
    assert "whole view" in caplog.text
    with pytest.raises(ValueError, match="prior"):
        reference_depth_loss(r, prior[:5], mask)


def test_reference_depth_prior_sources():
    H, W = 12, 16
    mask = np.zeros((H, W), bool)
    mask[3:8, 4:10] = True
    cam = Camera(K=np.eye(3), viewmat=np.eye(4), width=W, height=H, name="a.png")
    disp = np.random.default_rng(0).random((H, W)).astype(np.float32)
    scene = Scene([cam, cam], [np.zeros((H, W, 3), np.float32)] * 2, [mask, mask], np.zeros((0, 3)),
                  priors={"depth": {1: disp}})  # fmt: skip
    p = reference_depth_prior(scene, 1)
    prior, name = p
    assert name == DATASET_DEPTH_PRIOR and p.is_disparity and np.array_equal(prior, disp)
    yy, xx = np.mgrid[0:H, 0:W]
    gs = (2.0 + 0.05 * xx + 0.02 * yy).astype(np.float32)
    gs_obj = gs.copy()
    gs_obj[mask] = 0.5  # the object in front
    p0 = reference_depth_prior(scene, 0, gs_depth=torch.from_numpy(gs_obj))
    assert p0.name == GS_DEPTH_PRIOR and not p0.is_disparity
    assert np.array_equal(p0.prior[~mask], gs[~mask])
    assert np.abs(p0.prior[mask] - gs[mask]).max() < 0.25  # filled from the surroundings
    with pytest.raises(ValueError, match="no depth prior"):
        reference_depth_prior(scene, 0)


def test_inpaint_depth_constant_and_errors():
    m = np.zeros((10, 10), bool)
    m[3:6, 3:6] = True
    d = np.full((10, 10), 5.0, np.float32)
    d[m] = 0.0
    assert np.array_equal(inpaint_depth(d, m), np.full((10, 10), 5.0, np.float32))
    with pytest.raises(ValueError, match="nothing"):
        inpaint_depth(d, np.ones((10, 10), bool))
