"""Adaptive view weights W_n (coin_cl.gs.view_weights): the exact formula, edge cases, checkpoints."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from coin_cl.gs import view_weights
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.gs.refgs import view_weights as view_weights_of
from coin_cl.gs.view_weights import AdaptiveViewWeights


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
    off = view_weights_of(RefGSConfig(adaptive_weights=False), ref_view=0)
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
    assert view_weights.stable_sigmoid(0.0) == 0.5


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
    w2.load_state_dict(torch.load(buf, weights_only=True))
    assert w2.state_dict() == w.state_dict()
    a = [w.weight(views[i % 40], losses[i], step=i) for i in range(40, 80)]
    b = [w2.weight(views[i % 40], losses[i], step=i) for i in range(40, 80)]
    assert a == b and w.history == w2.history
