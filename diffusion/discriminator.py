"""The texture-enhancing discriminator of TE-D (paper 4.4): a pix2pix PatchGAN on small patches.

Patches from the initial inpaintings I^_n are "real", patches of the current GS renders R_n "fake".
Losses are the non-saturating GAN losses (Goodfellow et al. 2014), with softplus for stability:
    L_D   = E[softplus(-D(real))] + E[softplus(D(fake))]
    L_gen = E[softplus(-D(fake))]
Patches are drawn near the inpainted region by :func:`sample_patch_corners` (rule in its docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class PatchGANConfig:
    """ndf: channels of the first layer. n_layers: stride-2 layers (3 = pix2pix's 70x70 PatchGAN; on a
    64x64 patch the output is 6x6 logits, each seeing 70x70 input pixels, i.e. about the whole patch).
    norm: 'batch' (pix2pix), 'instance' or 'none'."""

    ndf: int = 64
    n_layers: int = 3
    norm: str = "batch"


class PatchDiscriminator(nn.Module):
    """pix2pix NLayerDiscriminator: (B, 3, P, P) in [0, 1] -> logits (B, 1, P/8 - 2, P/8 - 2) for the
    defaults (6x6 at P = 64). P >= 32 with 3 layers."""

    def __init__(self, cfg: PatchGANConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or PatchGANConfig()

        def norm(c: int) -> nn.Module:
            if cfg.norm == "batch":
                return nn.BatchNorm2d(c)
            if cfg.norm == "instance":
                return nn.InstanceNorm2d(c, affine=False)
            if cfg.norm == "none":
                return nn.Identity()
            raise ValueError(f"norm must be 'batch', 'instance' or 'none', got {cfg.norm!r}")

        use_bias = cfg.norm != "batch"  # a bias before BatchNorm is redundant (pix2pix does the same)
        layers: list[nn.Module] = [nn.Conv2d(3, cfg.ndf, 4, 2, 1), nn.LeakyReLU(0.2, True)]
        c = cfg.ndf
        for n in range(1, cfg.n_layers + 1):
            cn = cfg.ndf * min(2**n, 8)
            stride = 2 if n < cfg.n_layers else 1
            layers += [nn.Conv2d(c, cn, 4, stride, 1, bias=use_bias), norm(cn), nn.LeakyReLU(0.2, True)]
            c = cn
        layers.append(nn.Conv2d(c, 1, 4, 1, 1))
        self.net = nn.Sequential(*layers)
        for m in self.modules():  # pix2pix init: N(0, 0.02)
            if isinstance(m, nn.Conv2d):
                nn.init.normal_(m.weight, 0.0, 0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(2 * x - 1)


def d_loss(d_real: torch.Tensor, d_fake: torch.Tensor) -> torch.Tensor:
    """Non-saturating discriminator loss from logits (any shape): scalar."""
    return F.softplus(-d_real).mean() + F.softplus(d_fake).mean()


def g_loss(d_fake: torch.Tensor) -> torch.Tensor:
    """Non-saturating generator loss from logits of generated patches: scalar."""
    return F.softplus(-d_fake).mean()


def sample_patch_corners(
    mask: np.ndarray,
    n: int,
    patch: int = 64,
    p_near: float = 0.8,
    margin: int = 32,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Top-left corners (n, 2) int64 [y, x] of patch x patch windows inside an (H, W) image.

    Rule: with probability p_near a patch centre is drawn uniformly from the "near" band, the mask
    dilated by ``margin`` pixels (so the inpainted region and its immediate surroundings, where texture
    must match, dominate); otherwise uniformly over the whole image (so the discriminator also sees
    ordinary texture and does not learn "near a hole" as a cue). Empty masks use the whole image.
    Centres are then clamped so the window lies inside the image. H, W >= patch.
    """
    H, W = mask.shape
    if H < patch or W < patch:
        raise ValueError(f"image {H}x{W} is smaller than the patch size {patch}")
    if not 0.0 <= p_near <= 1.0:
        raise ValueError(f"p_near must be in [0, 1], got {p_near}")
    rng = rng or np.random.default_rng()
    m = np.asarray(mask, bool)
    if m.any() and margin > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        near = cv2.dilate(m.astype(np.uint8), k) > 0
    else:
        near = m
    ny, nx = np.nonzero(near)
    out = np.empty((n, 2), np.int64)
    for i in range(n):
        if ny.size and rng.random() < p_near:
            j = rng.integers(ny.size)
            cy, cx = ny[j], nx[j]
        else:
            cy, cx = rng.integers(H), rng.integers(W)
        out[i] = (min(max(cy - patch // 2, 0), H - patch), min(max(cx - patch // 2, 0), W - patch))
    return out


def crop_patches(img: torch.Tensor, corners: np.ndarray, patch: int = 64) -> torch.Tensor:
    """Patches (N, C, patch, patch) of img (C, H, W) at corners (N, 2) [y, x]; differentiable."""
    return torch.stack([img[:, y : y + patch, x : x + patch] for y, x in corners.tolist()])
