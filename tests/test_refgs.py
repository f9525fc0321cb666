"""Ref-GS switches (coin_cl.gs.refgs): the config's defaults, validation and schedules."""

from __future__ import annotations

import pytest

from coin_cl.gs.refgs import RefGSConfig


def test_config_defaults_and_validation():
    c = RefGSConfig()
    assert (c.lambda_r, c.lambda_depth, c.first_visit_weight, c.attn_mix) == (50.0, 10.0, 0.5, 1.0)
    assert RefGSConfig.from_dict(c.to_dict()) == c
    assert not c.attention_active(499, 1000) and c.attention_active(500, 1000)
    assert not RefGSConfig(feature_attention=False, attn_from=0.0).attention_active(10, 100)
    assert c.attn_lr(100)(0) == pytest.approx(0.01) and c.attn_lr(100)(100) == pytest.approx(1e-5)
    for bad in ({"lambda_r": 0}, {"lambda_r": float("nan")}, {"prune_min_fraction": 0},
                {"attn_mix": 0}, {"attn_heads": 0}, {"lambda_depth": -1}, {"attn_from": 2},
                {"aux_grad_ratio": -0.1}, {"aux_grad_ratio": float("inf")}):  # fmt: skip
        with pytest.raises(ValueError):
            RefGSConfig(**bad)


def test_builders_and_terms_follow_the_config():
    import numpy as np

    from coin_cl.gs.refgs import adaptive_weights_of, anchor_attention, refgs_terms, view_weights

    cfg = RefGSConfig(lambda_r=80.0, first_visit_weight=0.3, attn_heads=2, attn_head_dim=8, attn_mix=0.5,
                      attn_from=0.25, ring_frac=0.3, ring_min_px=2, attn_write_back=False)  # fmt: skip
    w = view_weights(cfg, 3)
    assert (w.ref_view, w.lambda_r, w.first_visit_weight, w.enabled) == (3, 80.0, 0.3, True)
    a = anchor_attention(cfg, 16)
    assert (a.feat_dim, a.heads, a.head_dim, a.mix) == (16, 2, 8, 0.5)
    masks = [np.zeros((4, 4), bool)] * 2
    terms = refgs_terms(cfg, 1, masks, 100, feat_dim=16, depth_prior=np.zeros((4, 4), np.float32))
    att = next(t for t in terms if t.name == "attention")
    assert att.start_step == 25.0 and (att.ring_frac, att.ring_min_px, att.write_back) == (0.3, 2, False)
    assert att.lr(0) == pytest.approx(0.01) and att.lr(100) == pytest.approx(1e-5)
    assert any(t.name == "ref_depth" for t in terms) and adaptive_weights_of(terms).lambda_r == 80.0
    # the depth priors are the auxiliary terms the trainer caps; the photometric loss is not
    assert {t.name for t in terms if t.auxiliary} == {"ref_depth"}
    plain = refgs_terms(RefGSConfig(depth_loss=False, feature_attention=False), 0, masks, 10)
    assert [t.name for t in plain] == [t.name for t in terms[:2]]  # photometric loss and scale reg only
    with pytest.raises(ValueError, match="depth prior"):
        refgs_terms(RefGSConfig(), 0, masks, 10)
