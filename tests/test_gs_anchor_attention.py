"""Anchor feature attention (coin_cl.gs.anchor_attention): the in/ring sets, the attention's rows,
gradients, caps, state and write-back."""

from __future__ import annotations

import io
import logging

import numpy as np
import pytest
import torch

from coin_cl.gs.anchor_attention import (
    AnchorAttention,
    attend_written_out,
    mask_anchor_sets,
    write_back_features,
)
from coin_cl.gs.refgs import RefGSConfig, anchor_attention
from coin_cl.scene.types import Camera


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
    with caplog.at_level(logging.DEBUG, logger="coin_cl.gs.anchor_attention"):
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
    a3.load_state_dict(torch.load(buf, weights_only=True))
    assert a3.n_calls == 1
    assert torch.equal(a1(f, in_idx, side_idx)[0], a3(f, in_idx, side_idx)[0])


def test_attention_write_back_and_apply_view():
    cam = _pinhole()
    mask = np.zeros((30, 40), bool)
    mask[10:20, 15:25] = True
    anchors = torch.tensor([_at_pixel(cam, 20.5, 15.5, 2.0), _at_pixel(cam, 12.5, 15.5, 2.0),
                            _at_pixel(cam, 5.5, 5.5, 2.0)])  # fmt: skip
    param = torch.nn.Parameter(torch.randn(3, 32))
    att = anchor_attention(RefGSConfig())
    out, info = att.apply_view(param, anchors, cam, mask)
    assert info["updated"].tolist() == [0] and torch.allclose(out[0], param[1].detach(), atol=1e-6)
    before = param.detach().clone()
    write_back_features(param, out, info["updated"])
    assert torch.allclose(param[0], before[1]) and torch.equal(param[1:], before[1:])


@pytest.mark.parametrize("heads,head_dim", [(4, 16), (8, 4), (2, 16)])  # value width below, above, equal
def test_fused_attention_matches_the_written_out_softmax_in_float64(heads, head_dim):
    torch.manual_seed(0)
    att = AnchorAttention(32, heads=heads, head_dim=head_dim, seed=3).double()
    f_in = torch.randn(37, 32, dtype=torch.float64, requires_grad=True)
    f_side = torch.randn(53, 32, dtype=torch.float64, requires_grad=True)
    up = torch.randn(37, 32, dtype=torch.float64)
    got, want = att.attend(f_in, f_side), attend_written_out(att, f_in, f_side)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    params = [f_in, f_side, *att.parameters()]
    g_got = torch.autograd.grad((got * up).sum(), params)
    g_want = torch.autograd.grad((want * up).sum(), params)
    for a, b in zip(g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    # float32, the training dtype: the same to rounding, and the same bits on every call (resume)
    att32 = AnchorAttention(32, heads=heads, head_dim=head_dim, seed=3)
    a32, b32 = f_in.detach().float(), f_side.detach().float()
    torch.testing.assert_close(
        att32.attend(a32, b32), attend_written_out(att32, a32, b32), rtol=1e-5, atol=1e-6
    )
    assert torch.equal(att32.attend(a32, b32), att32.attend(a32, b32))
