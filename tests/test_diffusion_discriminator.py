"""PatchGAN discriminator: shapes, gradients, learns sharp vs blurred; patch sampler rule."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from coin_cl.diffusion.discriminator import (
    PatchDiscriminator,
    PatchGANConfig,
    crop_patches,
    d_loss,
    g_loss,
    sample_patch_corners,
)


def test_shapes_and_gradients():
    D = PatchDiscriminator()
    x = torch.rand(2, 3, 64, 64, requires_grad=True)
    y = D(x)
    assert y.shape == (2, 1, 6, 6)
    g_loss(y).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is not None for p in D.parameters())
    assert d_loss(torch.zeros(3), torch.zeros(3)).item() == pytest.approx(2 * np.log(2))
    with pytest.raises(ValueError, match="norm"):
        PatchDiscriminator(PatchGANConfig(norm="layer"))


def _sharp(n, g):
    """Random high-frequency textures (checker-like noise upsampled by 2, so it has a spectrum)."""
    x = torch.rand(n, 3, 32, 32, generator=g)
    return F.interpolate(x, scale_factor=2, mode="nearest")


def _blur(x):
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0])
    k = (k[:, None] * k[None]) / 256
    w = k.expand(3, 1, 5, 5).contiguous()
    return F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), w, groups=3)


def test_separates_blurred_from_sharp():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    D = PatchDiscriminator(PatchGANConfig(ndf=8))
    opt = torch.optim.Adam(D.parameters(), lr=2e-4, betas=(0.5, 0.999))
    for _ in range(200):
        real = _sharp(8, g)
        fake = _blur(_sharp(8, g))  # same distribution, blurred: only texture tells them apart
        loss = d_loss(D(real), D(fake))
        opt.zero_grad()
        loss.backward()
        opt.step()
    # pix2pix keeps D in training mode (batch statistics of each real or fake batch), as here
    with torch.no_grad():
        real, fake = _sharp(32, g), _blur(_sharp(32, g))
        lr_, lf = D(real), D(fake)
        pr, pf = torch.sigmoid(lr_).mean((1, 2, 3)), torch.sigmoid(lf).mean((1, 2, 3))
    acc = 0.5 * ((pr > 0.5).float().mean() + (pf < 0.5).float().mean())
    assert acc > 0.95 and float(d_loss(lr_, lf)) < 0.5


def test_patch_sampler_probability_rule():
    H, W = 200, 300
    mask = np.zeros((H, W), bool)
    mask[90:110, 200:230] = True
    rng = np.random.default_rng(0)
    c = sample_patch_corners(mask, 2000, patch=64, p_near=0.8, margin=16, rng=rng)
    assert c.shape == (2000, 2) and c.min() >= 0
    assert (c[:, 0] <= H - 64).all() and (c[:, 1] <= W - 64).all()
    centre_y, centre_x = c[:, 0] + 32, c[:, 1] + 32
    near = (np.abs(centre_y - 100) <= 26 + 1) & (np.abs(centre_x - 215) <= 31 + 1)
    # 80 % from the near band plus the share of uniform draws that land in it
    band_frac = (52 * 62) / (H * W)
    assert abs(near.mean() - (0.8 + 0.2 * band_frac)) < 0.04
    c0 = sample_patch_corners(mask, 500, patch=64, p_near=0.0, rng=rng)
    assert np.abs(c0[:, 1] + 32 - 215).mean() > 40  # p_near = 0: uniform over the image
    ce = sample_patch_corners(np.zeros((H, W), bool), 10, rng=rng)
    assert ce.shape == (10, 2)
    img = torch.rand(3, H, W)
    p = crop_patches(img, c[:4])
    assert p.shape == (4, 3, 64, 64) and torch.equal(
        p[0], img[:, c[0, 0] : c[0, 0] + 64, c[0, 1] : c[0, 1] + 64]
    )
    with pytest.raises(ValueError, match="smaller than the patch"):
        sample_patch_corners(np.zeros((32, 32), bool), 1)
