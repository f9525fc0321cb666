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
                {"attn_mix": 0}, {"attn_heads": 0}, {"lambda_depth": -1}, {"attn_from": 2}):  # fmt: skip
        with pytest.raises(ValueError):
            RefGSConfig(**bad)
