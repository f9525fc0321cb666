"""CLG's no-worse guard (coin_cl.pipeline.clg_guard): each way an output can be worse than its input
is named, and `pick` chooses the candidate that passes with the lowest residual, or keeps the input."""

from __future__ import annotations

import cv2
import numpy as np

from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.clg_guard import colour_distance, no_worse, pick


def _textured(seed=0, h=48, w=64):
    rng = np.random.default_rng(seed)
    base = np.stack(np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h)), -1)
    img = np.concatenate([base, base[..., :1] * 0.5], -1) * 0.5 + 0.25
    return np.clip(img + 0.08 * rng.standard_normal((h, w, 1)), 0, 1).astype(np.float32)


def _mask(img):
    mask = np.zeros(img.shape[:2], bool)
    mask[14:34, 20:44] = True
    return mask


def _hue_noise(img, mask, seed=1):
    out = img.copy()
    out[mask] = np.random.default_rng(seed).uniform(0, 1, (int(mask.sum()), 3))  # hues the scene lacks
    return out


def test_no_worse_names_each_way_an_output_can_be_worse():
    cfg = CLGConfig()
    inp = _textured()
    mask = _mask(inp)
    assert no_worse(inp, inp.copy(), mask, {"residual_before": 0.1, "residual_after": 0.08}, cfg) == []
    blur = inp.copy()
    blur[mask] = cv2.GaussianBlur(inp, (0, 0), 4)[mask]
    assert any(w.startswith("texture") for w in no_worse(inp, blur, mask, {}, cfg))
    assert any(w.startswith("colour") for w in no_worse(inp, _hue_noise(inp, mask), mask, {}, cfg))
    why = no_worse(inp, inp.copy(), mask, {"residual_before": 0.05, "residual_after": 0.09}, cfg)
    assert why == ["residual to the reference 0.0500 -> 0.0900"]
    lifted = {"lifted_before": 0.05, "lifted_after": float("nan")}  # no depth: not a reason
    assert no_worse(inp, inp.copy(), mask, lifted, cfg) == []


def test_colour_distance_grows_with_hues_the_surroundings_lack():
    inp = _textured()
    mask = _mask(inp)
    shifted = np.roll(inp, 1, axis=1)
    assert colour_distance(_hue_noise(inp, mask), mask) > 3 * colour_distance(shifted, mask)
    assert np.isnan(colour_distance(inp, np.zeros_like(mask)))  # an empty mask has no statistics
    assert np.isnan(colour_distance(inp, np.ones_like(mask)))  # a full one has no ring


def test_pick_takes_the_passing_candidate_with_the_lowest_residual():
    cfg = CLGConfig()
    inp = _textured()
    mask = _mask(inp)
    other = _textured(seed=2)  # as textured as the input, same hues
    rec = {"residual_before": 0.08}
    cands = [
        # the closest to the reference, but hue noise
        (_hue_noise(inp, mask), rec | {"colour_match": True, "residual_after": 0.03}),
        (inp.copy(), rec | {"colour_match": False, "residual_after": 0.06}),
        (other, rec | {"colour_match": None, "residual_after": 0.05}),
    ]
    out, chosen = pick(inp, cands, mask, cfg)
    assert out is cands[2][0] and chosen["residual_after"] == 0.05
    assert [bool(c["worse"]) for c in chosen["candidates"]] == [True, False, False]
    # none passes: the input, with the first candidate's reasons
    worse = [(c[0], c[1] | {"residual_after": 0.09}) for c in cands]
    out, kept = pick(inp, worse, mask, cfg)
    assert out is inp and kept["status"] == "kept input"
    assert any(w.startswith("colour") for w in kept["kept_because"])
    assert kept["residual_written"] == 0.08
    # an unmeasured residual (no support) ranks after a measured one, wherever it stands in the list
    unmeasured = [
        (inp.copy(), rec | {"residual_after": float("nan")}),
        (other, rec | {"residual_after": 0.07}),
    ]
    out, chosen = pick(inp, unmeasured, mask, cfg)
    assert out is other and chosen["residual_after"] == 0.07
    # a single candidate records no candidate list
    _, single = pick(inp, [(inp.copy(), rec | {"residual_after": 0.05})], mask, cfg)
    assert "candidates" not in single
