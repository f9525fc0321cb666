"""Ref-GS building blocks (coin_cl.gs.refgs): targets, pruning, adaptive weights, anchor attention,
reference depth loss and prior, reference choice."""

from __future__ import annotations

import io
import logging
import math

import numpy as np
import pytest
import torch

from coin_cl.gs import refgs
from coin_cl.gs.refgs import (
    DATASET_DEPTH_PRIOR,
    GS_DEPTH_PRIOR,
    AdaptiveViewWeights,
    AnchorAttention,
    RefGSConfig,
    choose_reference,
    composite_targets,
    fit_affine,
    inpaint_depth,
    mask_anchor_sets,
    prune_points_in_masks,
    reference_depth_loss,
    reference_depth_prior,
    resolve_reference,
    write_back_features,
)
from coin_cl.scene.types import Camera, Scene

# ---------------------------------------------------------------------------------------------
# config and targets


def test_config_defaults_and_validation():
    c = RefGSConfig()
    assert (c.lambda_r, c.lambda_depth, c.first_visit_weight, c.attn_mix) == (50.0, 10.0, 0.5, 1.0)
    assert RefGSConfig.from_dict(c.to_dict()) == c
    assert not c.attention_active(499, 1000) and c.attention_active(500, 1000)
    assert not RefGSConfig(feature_attention=False, attn_from=0.0).attention_active(10, 100)
    assert c.attn_lr(100)(0) == pytest.approx(0.01) and c.attn_lr(100)(100) == pytest.approx(1e-5)
    for bad in ({"lambda_r": 0}, {"lambda_r": float("nan")}, {"prune_min_fraction": 0},
                {"attn_mix": 0}, {"attn_heads": 0}, {"lambda_depth": -1}, {"attn_from": 2}):  # fmt: skip
        with pytest.raises(ValueError):
            RefGSConfig(**bad)


def test_composite_targets_numpy_and_torch():
    rng = np.random.default_rng(0)
    inp = rng.random((5, 6, 3), dtype=np.float32)
    img = rng.random((5, 6, 3), dtype=np.float32)
    m = np.zeros((5, 6), bool)
    m[1:3, 2:5] = True
    out = composite_targets(inp, img, m)
    assert np.array_equal(out[m], inp[m]) and np.array_equal(out[~m], img[~m])
    tout = composite_targets(torch.from_numpy(inp), torch.from_numpy(img), torch.from_numpy(m))
    assert isinstance(tout, torch.Tensor) and np.array_equal(tout.numpy(), out)
    with pytest.raises(ValueError, match="mask"):
        composite_targets(inp, img, m[:4])
    with pytest.raises(ValueError):
        composite_targets(inp, img[:4], m)


# ---------------------------------------------------------------------------------------------
# pruning on the synthetic room


@pytest.fixture(scope="module")
def room():
    """Six low-resolution cameras around the synthetic room's object, with ray-cast object masks."""
    from coin_cl.scene import synthetic as syn

    boxes = syn.default_room(0)
    obj = next(b for b in boxes if b.is_object)
    cams = syn.arc_cameras(6, 90, 64, 48, obj.center, seed=0)
    masks = []
    for c in cams:
        ys, xs = np.mgrid[0 : c.height, 0 : c.width]
        t = syn.trace(boxes, c, xs.ravel() + 0.5, ys.ravel() + 0.5, colour=False)
        masks.append(t["object"].reshape(c.height, c.width))
    return boxes, obj, cams, masks


def _brute_votes(points, cams, masks):
    """Independent count via scene.types.Camera.project / in_image, one point at a time."""
    seen = np.zeros(len(points), int)
    inside = np.zeros(len(points), int)
    for c, m in zip(cams, masks):
        for j, p in enumerate(points):
            uv, z = c.project(p[None])
            if z[0] > 0.01 and c.in_image(uv)[0]:
                seen[j] += 1
                inside[j] += int(m[int(np.floor(uv[0, 1])), int(np.floor(uv[0, 0]))])
    return seen, inside


def test_prune_removes_exactly_points_in_masks(room):
    boxes, obj, cams, masks = room
    assert all(m.any() for m in masks)
    rng = np.random.default_rng(1)
    # Points well inside the object (a 40% margin: bigger than a pixel's footprint there).
    local = rng.uniform(-0.6, 0.6, (150, 3)) * obj.half
    on_obj = local @ obj.R.T + obj.center
    # Points on the far wall and on the floor in front of it.
    wall = np.stack([rng.uniform(-2.5, 2.5, 100), np.full(100, 2.99), rng.uniform(0.2, 2.3, 100)], 1)
    floor = np.stack([rng.uniform(-2.5, 2.5, 100), rng.uniform(1.0, 2.5, 100), np.full(100, 0.01)], 1)
    # Points on the table top around the object: inside the mask in some views only.
    top = np.stack([rng.uniform(-0.5, 0.5, 150), rng.uniform(-0.4, 0.4, 150), np.full(150, 0.5)], 1)
    pts = np.concatenate([on_obj, wall, floor, top]).astype(np.float32)

    seen, inside = _brute_votes(pts, cams, masks)
    for frac in (0.5, 1.0):
        res = prune_points_in_masks(pts, cams, masks, min_fraction=frac)
        expected = (seen >= 1) & (inside >= frac * seen)
        assert np.array_equal(~res.keep, expected)
        assert res.n_removed == int(expected.sum())
        assert np.array_equal(res.points, pts[res.keep]) and res.points.dtype == np.float32
    res = prune_points_in_masks(pts, cams, masks, min_fraction=0.5)
    assert not res.keep[:150].any()  # every object point goes
    assert (inside[150:] == 0).sum() > 100 and res.keep[inside == 0].all()  # never in a mask: stays
    # Background behind the object is inside the masks from part of the arc; there is no
    # occlusion test (the hole's background is inpainted anyway): it goes where that is most views.
    behind = (inside[150:] > 0) & (inside[150:] < seen[150:])
    b_in, b_seen = inside[150:][behind], seen[150:][behind]
    assert behind.any() and np.array_equal(~res.keep[150:][behind], 2 * b_in >= b_seen)
    # Table-top points partly hidden by the object: only some go at 0.5, fewer at 1.0.
    n_top_half = int((~res.keep[350:]).sum())
    n_top_all = int((~prune_points_in_masks(pts, cams, masks, min_fraction=1.0).keep[350:]).sum())
    assert 0 <= n_top_all <= n_top_half < 150


def test_prune_accepts_torch_inputs_and_checks_input(room):
    _, obj, cams, masks = room
    # Cameras built from torch tensors, masks as tensors.
    gcams = [Camera(torch.from_numpy(c.K), torch.from_numpy(c.viewmat), c.width, c.height) for c in cams]
    tmasks = [torch.from_numpy(m) for m in masks]
    pts = obj.center[None] + np.zeros((3, 3))
    assert prune_points_in_masks(pts, gcams, tmasks).n_removed == 3
    # A point behind every camera is seen by none and kept.
    far = np.array([[0.0, 0.0, 100.0]])
    assert prune_points_in_masks(far, cams, masks).n_removed == 0
    with pytest.raises(ValueError, match="cameras"):
        prune_points_in_masks(pts, cams, masks[:-1])
    with pytest.raises(ValueError, match="mask"):
        prune_points_in_masks(pts, cams[:1], [masks[0][:10]])
    with pytest.raises(ValueError, match="min_fraction"):
        prune_points_in_masks(pts, cams, masks, min_fraction=0.0)


# ---------------------------------------------------------------------------------------------
# adaptive view weights


def _w(lam, now, prev):
    return 1.0 / (1.0 + math.exp(lam * (now - prev)))


def test_weights_exact_formula_on_sequence():
    w = AdaptiveViewWeights(ref_view=0, lambda_r=50.0)
    seq = [(1, 0.30), (2, 0.20), (0, 0.5), (1, 0.32), (2, 0.15), (1, 0.32), (0, 0.1), (1, 0.25)]
    got = [w.weight(v, L, step=i) for i, (v, L) in enumerate(seq)]
    expect = [0.5, 0.5, 50.0, _w(50, 0.32, 0.30), _w(50, 0.15, 0.20), 0.5, 50.0, _w(50, 0.25, 0.32)]
    assert got == pytest.approx(expect, rel=1e-12, abs=0)
    assert got[3] < 0.5 < got[4]  # a rising loss is down-weighted, a falling one up-weighted
    assert [h["prev"] for h in w.history] == [None, None, None, 0.30, 0.20, 0.32, 0.5, 0.32]
    s = w.summary()
    assert s[1]["visits"] == 4 and s[0]["last_weight"] == 50.0


def test_weights_reference_first_visit_and_disabled():
    w = AdaptiveViewWeights(ref_view="r", lambda_r=100.0, first_visit_weight=0.25)
    assert w.weight("r", 9.0) == 100.0 and w.weight("r", 0.0) == 100.0 and w.weight("r", 5.0) == 100.0
    assert w.weight("a", 0.1) == 0.25
    off = AdaptiveViewWeights.from_config(RefGSConfig(adaptive_weights=False), ref_view=0)
    assert [off.weight(v, L) for v, L in [(0, 1.0), (1, 1.0), (1, 2.0)]] == [1.0, 1.0, 1.0]


def test_weights_stable_for_huge_differences_and_reject_nan():
    w = AdaptiveViewWeights(ref_view=0, lambda_r=50.0)
    w.weight(1, 0.0)
    assert w.weight(1, 1e6) == 0.0  # exp(+5e7) would overflow: stable form gives 0
    assert w.weight(1, -1e6) == 1.0
    w.weight(2, 1e308)
    assert w.weight(2, -1e308) == 1.0
    for bad in (float("nan"), float("inf"), torch.tensor(float("nan"))):
        with pytest.raises(ValueError, match="loss"):
            w.weight(3, bad)
    assert refgs.stable_sigmoid(0.0) == 0.5


def test_weights_checkpoint_round_trip_is_exact():
    rng = np.random.default_rng(3)
    w = AdaptiveViewWeights(ref_view=2, lambda_r=50.0)
    views = rng.integers(0, 5, 40).tolist()
    losses = rng.random(80).tolist()
    for i in range(40):
        w.weight(views[i], losses[i], step=i)
    buf = io.BytesIO()
    torch.save(w.state_dict(), buf)
    buf.seek(0)
    w2 = AdaptiveViewWeights(ref_view=None)
    w2.load_state_dict(torch.load(buf, weights_only=False))
    assert w2.state_dict() == w.state_dict()
    a = [w.weight(views[i % 40], losses[i], step=i) for i in range(40, 80)]
    b = [w2.weight(views[i % 40], losses[i], step=i) for i in range(40, 80)]
    assert a == b and w.history == w2.history


# ---------------------------------------------------------------------------------------------
# anchor attention


def _pinhole(W=40, H=30, f=30.0) -> Camera:
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    return Camera(K, torch.eye(4), W, H, "c")


def _at_pixel(cam: Camera, u: float, v: float, z: float) -> list[float]:
    K = cam.K
    return [(u - float(K[0, 2])) / float(K[0, 0]) * z, (v - float(K[1, 2])) / float(K[1, 1]) * z, z]


def test_mask_anchor_sets():
    cam = _pinhole()
    mask = np.zeros((30, 40), bool)
    mask[10:20, 15:25] = True  # 10x10: ring width max(4, 0.5 * 10) = 5 px
    anchors = torch.tensor(
        [
            _at_pixel(cam, 20.5, 15.5, 2.0),  # 0 in mask
            _at_pixel(cam, 15.5, 10.5, 5.0),  # 1 in mask (corner pixel)
            _at_pixel(cam, 12.5, 15.5, 2.0),  # 2 ring (3 px left of the mask)
            _at_pixel(cam, 20.5, 22.5, 3.0),  # 3 ring (3 px below)
            _at_pixel(cam, 5.5, 15.5, 2.0),  # 4 outside the ring (10 px away)
            [0.0, 0.0, -2.0],  # 5 behind the camera (would project at the centre: in the mask)
            _at_pixel(cam, 60.0, 15.5, 2.0),  # 6 right of the image
            _at_pixel(cam, 20.5, 15.5, 0.001),  # 7 in front of the near plane
        ]
    )
    in_idx, side_idx = mask_anchor_sets(anchors, cam, mask)
    assert in_idx.tolist() == [0, 1] and side_idx.tolist() == [2, 3]
    # Numpy anchors give the same sets.
    i2, s2 = mask_anchor_sets(anchors.numpy(), cam, mask)
    assert torch.equal(i2, in_idx) and torch.equal(s2, side_idx)
    # A wider ring reaches anchor 4.
    assert 4 in mask_anchor_sets(anchors, cam, mask, ring_frac=1.2)[1].tolist()
    with pytest.raises(ValueError, match="mask"):
        mask_anchor_sets(anchors, cam, mask.T)


def test_attention_changes_only_in_mask_rows():
    torch.manual_seed(0)
    f = torch.randn(30, 32)
    att = AnchorAttention(32, heads=4, head_dim=8, seed=1)
    in_idx, side_idx = torch.tensor([2, 5, 7]), torch.tensor([0, 1, 10, 11, 20])
    out, info = att(f, in_idx, side_idx)
    changed = (out != f).any(1)
    assert changed[in_idx].all() and changed.sum() == 3
    assert info["n_in_used"] == 3 and info["n_side_used"] == 5 and info["skipped"] is None
    assert torch.equal(info["updated"], in_idx)
    # Each head's output is a convex combination of the side features in its channels.
    side = f[side_idx].view(5, 4, 8)
    o = out[in_idx].view(3, 4, 8)
    assert (o <= side.amax(0) + 1e-6).all() and (o >= side.amin(0) - 1e-6).all()


def test_attention_identical_side_features_replace():
    torch.manual_seed(0)
    f = torch.randn(12, 32)
    s = torch.randn(32)
    side_idx = torch.tensor([0, 3, 4, 9])
    f[side_idx] = s
    att = AnchorAttention(32, heads=8, head_dim=4, seed=0)
    out, _ = att(f, torch.tensor([1, 2, 11]), side_idx)
    assert torch.allclose(out[[1, 2, 11]], s.expand(3, 32), atol=1e-6)
    # EMA blend: mix * side + (1 - mix) * old.
    ema = AnchorAttention(32, heads=8, head_dim=4, mix=0.25, seed=0)
    out2, _ = ema(f, torch.tensor([1]), side_idx)
    assert torch.allclose(out2[1], 0.25 * s + 0.75 * f[1], atol=1e-6)


def test_attention_empty_sets_skip(caplog):
    f = torch.randn(5, 32)
    att = AnchorAttention(32)
    with caplog.at_level(logging.DEBUG, logger="coin_cl.gs.refgs"):
        out, info = att(f, torch.tensor([], dtype=torch.long), torch.tensor([1, 2]))
        out2, info2 = att(f, torch.tensor([0]), torch.zeros(0, dtype=torch.long))
    assert out is f and out2 is f
    assert info["skipped"] == "no anchors inside the mask" and info2["skipped"] == "no anchors in the ring"
    assert att.n_skipped == 2 and att.n_calls == 2
    assert "skipped" in caplog.text
    with pytest.raises(ValueError, match="overlap"):
        att(f, torch.tensor([0, 1]), torch.tensor([1, 2]))
    with pytest.raises(IndexError):
        att(f, torch.tensor([7]), torch.tensor([1]))


def test_attention_gradients_flow():
    torch.manual_seed(0)
    f = torch.randn(20, 32, requires_grad=True)
    att = AnchorAttention(32, heads=4, head_dim=8)
    out, _ = att(f, torch.tensor([0, 1, 2]), torch.tensor([5, 6, 7, 8]))
    up = torch.randn(20, 32)
    (out * up).sum().backward()
    for name, p in att.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    g = f.grad
    assert g[[0, 1, 2, 5, 6, 7, 8]].abs().sum(1).gt(0).all()  # queries, and keys/values
    assert torch.equal(g[[3, 4]], up[[3, 4]])  # untouched rows: identity


def test_attention_caps_seeded_and_state_round_trip():
    f = torch.randn(100, 32)
    in_idx, side_idx = torch.arange(0, 50), torch.arange(50, 100)
    a1 = AnchorAttention(32, max_in=7, max_side=9, seed=3)
    a2 = AnchorAttention(32, max_in=7, max_side=9, seed=3)
    o1, i1 = a1(f, in_idx, side_idx)
    o2, i2 = a2(f, in_idx, side_idx)
    assert torch.equal(o1, o2) and i1["n_in_used"] == 7 and i1["n_side_used"] == 9
    assert (o1 != f).any(1).sum() == 7 and torch.equal(i1["updated"], i2["updated"])
    sd = a1.state_dict()
    buf = io.BytesIO()
    torch.save(sd, buf)
    buf.seek(0)
    a3 = AnchorAttention(32, max_in=7, max_side=9, seed=99)
    a3.load_state_dict(torch.load(buf, weights_only=False))
    assert a3.n_calls == 1
    assert torch.equal(a1(f, in_idx, side_idx)[0], a3(f, in_idx, side_idx)[0])


def test_attention_write_back_and_apply_view():
    cam = _pinhole()
    mask = np.zeros((30, 40), bool)
    mask[10:20, 15:25] = True
    anchors = torch.tensor([_at_pixel(cam, 20.5, 15.5, 2.0), _at_pixel(cam, 12.5, 15.5, 2.0),
                            _at_pixel(cam, 5.5, 5.5, 2.0)])  # fmt: skip
    param = torch.nn.Parameter(torch.randn(3, 32))
    att = AnchorAttention.from_config(RefGSConfig())
    out, info = att.apply_view(param, anchors, cam, mask)
    assert info["updated"].tolist() == [0] and torch.allclose(out[0], param[1].detach(), atol=1e-6)
    before = param.detach().clone()
    write_back_features(param, out, info["updated"])
    assert torch.allclose(param[0], before[1]) and torch.equal(param[1:], before[1:])


# ---------------------------------------------------------------------------------------------
# reference depth


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
    with caplog.at_level(logging.WARNING, logger="coin_cl.gs.refgs"):
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


# ---------------------------------------------------------------------------------------------
# reference choice


def _masks():
    H, W = 20, 30
    small = np.zeros((H, W), bool)
    small[8:12, 13:17] = True  # central, small
    big_corner = np.zeros((H, W), bool)
    big_corner[0:10, 0:12] = True  # larger but in a corner
    big_centre = np.zeros((H, W), bool)
    big_centre[5:15, 9:21] = True  # as large, central
    return [small, big_corner, big_centre, big_centre.copy(), np.zeros((H, W), bool)]


def test_choose_reference_rule():
    ms = _masks()
    assert refgs.reference_score(ms[2]) > refgs.reference_score(ms[1]) > 0
    assert refgs.reference_score(ms[4]) == 0.0
    assert choose_reference(ms) == 2  # ties (2 and 3) go to the lowest index
    assert choose_reference(ms, train_idx=[0, 1, 3, 4]) == 3
    assert choose_reference(ms, train_idx=[0, 1]) == 1  # 0.2 x 0.43 beats 0.027 x 0.99


def test_choose_reference_from_scene_and_resolve():
    ms = _masks()
    cams = [Camera(K=np.eye(3), viewmat=np.eye(4), width=30, height=20, name=f"img_{i:03d}.png")
            for i in range(5)]  # fmt: skip
    scene = Scene(cams, [np.zeros((20, 30, 3), np.float32)] * 5, ms, np.zeros((0, 3)),
                  train_idx=[0, 1, 3, 4], test_idx=[2])  # fmt: skip
    assert choose_reference(scene) == 3
    assert choose_reference(scene, ref="img_001.png") == 1
    assert choose_reference(scene, ref="img_001") == 1
    assert choose_reference(scene, ref=4) == 4
    assert choose_reference(scene, ref="0") == 0
    with pytest.raises(ValueError, match="not a training view"):
        choose_reference(scene, ref=2)
    with pytest.raises(ValueError, match="no view of that name"):
        choose_reference(scene, ref="nope.png")
    with pytest.raises(ValueError, match="not a training view"):
        resolve_reference(17, scene.names, scene.train_idx)
    with pytest.raises(ValueError):
        resolve_reference(1.5, scene.names, scene.train_idx)  # type: ignore[arg-type]
