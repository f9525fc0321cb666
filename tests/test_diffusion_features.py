"""Features: DINO loader with the official key names (random values), joint-bilateral upsampler,
analytic descriptor (translation-equivariant, brightness/contrast invariant, differentiable)."""

import logging

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from coin_cl.diffusion.features import (
    AnalyticFeatures,
    DinoFeatures,
    joint_bilateral_upsample,
    load_dino,
    make_feature_extractor,
)


def _official_vits16_state_dict(seed=0):
    """Keys and shapes of dino_deitsmall16_pretrain.pth (facebookresearch/dino), random values."""
    g = torch.Generator().manual_seed(seed)
    d, sd = 384, {}

    def r(*shape, s=0.02):
        return torch.randn(*shape, generator=g) * s

    sd["cls_token"] = r(1, 1, d)
    sd["pos_embed"] = r(1, 197, d)
    sd["patch_embed.proj.weight"] = r(d, 3, 16, 16)
    sd["patch_embed.proj.bias"] = r(d)
    for i in range(12):
        p = f"blocks.{i}."
        sd[p + "norm1.weight"], sd[p + "norm1.bias"] = 1 + r(d), r(d)
        sd[p + "attn.qkv.weight"], sd[p + "attn.qkv.bias"] = r(3 * d, d), r(3 * d)
        sd[p + "attn.proj.weight"], sd[p + "attn.proj.bias"] = r(d, d), r(d)
        sd[p + "norm2.weight"], sd[p + "norm2.bias"] = 1 + r(d), r(d)
        sd[p + "mlp.fc1.weight"], sd[p + "mlp.fc1.bias"] = r(4 * d, d), r(4 * d)
        sd[p + "mlp.fc2.weight"], sd[p + "mlp.fc2.bias"] = r(d, 4 * d), r(d)
    sd["norm.weight"], sd["norm.bias"] = 1 + r(d), r(d)
    return sd


def test_dino_loads_official_keys_and_gradients_reach_image(tmp_path, monkeypatch):
    sd = _official_vits16_state_dict()
    path = tmp_path / "dino_deitsmall16_pretrain.pth"
    torch.save(sd, path)
    vit = load_dino(path)
    assert torch.equal(vit.state_dict()["blocks.11.mlp.fc2.weight"], sd["blocks.11.mlp.fc2.weight"])
    img = torch.rand(1, 3, 64, 48, generator=torch.Generator().manual_seed(1), requires_grad=True)
    tok = vit(img)
    assert tok.shape == (1, 384, 4, 3) and torch.isfinite(tok).all()
    feats = DinoFeatures(vit)(img)
    assert feats.shape == (1, 384, 64, 48)
    feats.square().mean().backward()
    assert img.grad is not None and img.grad.abs().sum() > 0
    # a training checkpoint wrapping the teacher with prefixes loads too
    torch.save({"teacher": {"backbone." + k: v for k, v in sd.items()}}, tmp_path / "ckpt.pth")
    assert torch.equal(load_dino(tmp_path / "ckpt.pth").pos_embed, sd["pos_embed"])
    monkeypatch.setenv("COIN_DINO_WEIGHTS", str(path))
    ext, name = make_feature_extractor()
    assert name.startswith("DINO ViT-S/16")


def test_dino_bad_files(tmp_path, monkeypatch):
    monkeypatch.delenv("COIN_DINO_WEIGHTS", raising=False)
    with pytest.raises(FileNotFoundError, match="COIN_DINO_WEIGHTS"):
        load_dino()
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        load_dino(tmp_path / "nope.pth")
    sd = _official_vits16_state_dict()
    del sd["blocks.3.attn.proj.bias"]
    torch.save(sd, tmp_path / "broken.pth")
    with pytest.raises(KeyError, match=r"blocks\.3\.attn\.proj\.bias"):
        load_dino(tmp_path / "broken.pth")


def test_joint_bilateral_upsampler_snaps_to_edges():
    # a vertical colour edge in the guide at x = 20 (inside low-res cell 2 of width 8); features are a
    # step across cells. Upsampled features follow the guide's edge, not the cell grid.
    H = W = 32
    guide = torch.zeros(1, 3, H, W)
    guide[..., 20:] = 1.0
    feat = torch.zeros(1, 1, 4, 4)
    feat[..., 3:] = 1.0  # cell 3 (x >= 24) is "right"; cell 2 straddles the edge
    feat[..., 2] = 0.5
    up = joint_bilateral_upsample(feat, guide, radius=1, sigma_spatial=1.0, sigma_range=0.1)
    assert up.shape == (1, 1, H, W)
    row = up[0, 0, 10]
    assert row[21] > 0.6 and row[18] < 0.4  # the jump lands at the image edge (x = 20)
    const = joint_bilateral_upsample(torch.full((1, 5, 4, 4), 0.3), guide)
    assert torch.allclose(const, torch.full_like(const, 0.3))  # weights are normalised
    with pytest.raises(ValueError, match="integer multiple"):
        joint_bilateral_upsample(feat, torch.zeros(1, 3, 30, 32))


def _natural_like(n=96, seed=0):
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(rng.random((1, 3, n, n))).float()
    for _ in range(2):  # some spatial correlation (structure at several scales)
        x = F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), 3, stride=1)
    return (x - x.min()) / (x.max() - x.min())


def test_analytic_translation_equivariant():
    ext = AnalyticFeatures()
    img = _natural_like()
    f = ext(img)
    assert f.shape == (1, ext.channels, 96, 96) and ext.channels == 24
    sh = torch.roll(img, shifts=(5, -7), dims=(2, 3))
    fs = ext(sh)
    m = 32  # compare away from the borders and the roll's wrap seam (3.5 sigma + normalisation window)
    a = torch.roll(f, shifts=(5, -7), dims=(2, 3))[..., m:-m, m:-m]
    b = fs[..., m:-m, m:-m]
    assert (a - b).abs().max() < 1e-3 * a.abs().max()  # float32 rounding only


def test_analytic_brightness_contrast_invariant_and_structure_sensitive():
    ext = AnalyticFeatures()
    img = _natural_like()
    f = ext(img)
    f2 = ext(0.5 * img + 0.3)  # contrast halved, brightness raised
    cos = F.cosine_similarity(f, f2, dim=1).mean()
    assert cos > 0.99 and (f - f2).abs().max() < 0.05 * f.abs().max()
    other = ext(_natural_like(seed=1))
    assert F.cosine_similarity(f, other, dim=1).mean() < 0.5  # different structure: different features
    flat = ext(torch.full((1, 3, 64, 64), 0.4))
    assert flat.abs().max() < 1e-3  # no structure, no response


def test_analytic_differentiable_and_default_named(monkeypatch, caplog):
    img = _natural_like(48).requires_grad_(True)
    AnalyticFeatures()(img).square().mean().backward()
    assert torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    monkeypatch.delenv("COIN_DINO_WEIGHTS", raising=False)
    with caplog.at_level(logging.INFO):
        _, name = make_feature_extractor()
    assert name == "analytic oriented-derivative features" and name in caplog.text
