"""Features for the consistency energy (paper 4.3): high-frequency structure features of an image.

Two extractors, both differentiable with respect to the input image (the guidance gradient flows
through them), both mapping an image (B, 3, H, W) float in [0, 1] to features (B, C, H, W):

- "DINO ViT-S/16 + joint-bilateral upsampling": the paper's DINO ViT-S/16 in plain torch, loading the
  official checkpoint (``dino_deitsmall16_pretrain.pth``, its own key names) from a local file
  (argument or ``COIN_DINO_WEIGHTS``), L2-normalised patch tokens upsampled to the image size by a
  differentiable joint-bilateral upsampler guided by the image. This replaces FeatUp, whose weights
  cannot be had here either; it is named as what it is.
- "analytic oriented-derivative features" (the embedded default, no weights): oriented first and second
  derivative-of-Gaussian responses of the luminance at several scales and orientations, divided by the
  local response energy. What it responds to: edges (first derivative) and bars/lines (second
  derivative) by orientation and scale, i.e. local structure and texture. Flat regions and smooth
  shading give ~0; adding a constant to the image changes nothing (derivatives); multiplying it by a
  constant changes nothing either (local normalisation), so the cosine term of the energy compares
  structure, not brightness or contrast. It is translation-equivariant (convolutions only).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from coin_cl.checkpoint import load_checkpoint  # torch only: no engine, no OpenCL

log = logging.getLogger(__name__)

DINO_ENV = "COIN_DINO_WEIGHTS"
DINO_NAME = "DINO ViT-S/16 + joint-bilateral upsampling"
ANALYTIC_NAME = "analytic oriented-derivative features"
_IMNET_MEAN = (0.485, 0.456, 0.406)
_IMNET_STD = (0.229, 0.224, 0.225)


# ----------------------------------------------------------------------------------------------------
# DINO ViT-S/16 (key names as facebookresearch/dino's vision_transformer.py state dict)


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self.qkv(x).reshape(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v)
        return self.proj(y.transpose(1, 2).reshape(B, N, C))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class _Block(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = _Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = _Mlp(dim, 4 * dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class DinoViT(nn.Module):
    """DINO ViT (default ViT-S/16: dim 384, depth 12, 6 heads, trained at 224 = 14x14 patches).

    forward: image (B, 3, H, W) in [0, 1], H and W multiples of the patch size -> patch tokens of the
    last block after the final norm, (B, dim, H/16, W/16). Positional embeddings are bicubically
    interpolated to other grid sizes, as DINO does.
    """

    def __init__(
        self, dim: int = 384, depth: int = 12, heads: int = 6, patch: int = 16, grid: int = 14
    ) -> None:
        super().__init__()
        self.patch = patch
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv2d(3, dim, patch, stride=patch)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, dim))
        self.blocks = nn.ModuleList([_Block(dim, heads) for _ in range(depth)])
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.register_buffer("mean", torch.tensor(_IMNET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMNET_STD).view(1, 3, 1, 1), persistent=False)

    def _pos(self, h: int, w: int) -> torch.Tensor:
        n = self.pos_embed.shape[1] - 1
        g = int(round(math.sqrt(n)))
        if g * g == h * w and h == w:
            return self.pos_embed
        grid = self.pos_embed[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
        return torch.cat([self.pos_embed[:, :1], grid.flatten(2).transpose(1, 2)], dim=1)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        B, _, H, W = img.shape
        if H % self.patch or W % self.patch:
            raise ValueError(f"DINO input {H}x{W} must be a multiple of the patch size {self.patch}")
        x = self.patch_embed.proj((img - self.mean) / self.std)
        h, w = x.shape[-2:]
        x = torch.cat([self.cls_token.expand(B, -1, -1), x.flatten(2).transpose(1, 2)], dim=1)
        x = x + self._pos(h, w)
        for blk in self.blocks:
            x = blk(x)
        x = self.norm(x)
        return x[:, 1:].transpose(1, 2).reshape(B, -1, h, w)


def load_dino(path: str | os.PathLike | None = None) -> DinoViT:
    """DINO ViT-S/16 from the official checkpoint file (argument or $COIN_DINO_WEIGHTS).

    Accepts the plain state dict (dino_deitsmall16_pretrain.pth) and full training checkpoints
    ({'teacher': ...} with 'module.'/'backbone.' prefixes). Raises FileNotFoundError / KeyError with
    what is missing and what to pass.
    """
    p = path if path is not None else os.environ.get(DINO_ENV)
    if not p:
        raise FileNotFoundError(
            f"no DINO weights given: pass a path or set {DINO_ENV} to "
            "dino_deitsmall16_pretrain.pth (nothing is downloaded)"
        )
    p = Path(p)
    if not p.is_file():
        raise FileNotFoundError(
            f"DINO weights file {p} does not exist (set {DINO_ENV} or pass the path "
            "to dino_deitsmall16_pretrain.pth)"
        )
    sd = load_checkpoint(p, f"set {DINO_ENV} to dino_deitsmall16_pretrain.pth", what="DINO weight file")
    if "teacher" in sd:
        sd = sd["teacher"]
    sd = {k.removeprefix("module.").removeprefix("backbone."): v for k, v in sd.items()}
    sd = {k: v for k, v in sd.items() if not k.startswith("head.")}
    if "pos_embed" not in sd or "patch_embed.proj.weight" not in sd:
        raise KeyError(f"{p} is not a DINO ViT state dict (no pos_embed / patch_embed.proj.weight)")
    dim, _, patch, _ = sd["patch_embed.proj.weight"].shape
    depth = 1 + max(int(k.split(".")[1]) for k in sd if k.startswith("blocks."))
    grid = int(round(math.sqrt(sd["pos_embed"].shape[1] - 1)))
    model = DinoViT(dim=dim, depth=depth, heads=dim // 64, patch=patch, grid=grid)
    res = model.load_state_dict(sd, strict=False)
    if res.missing_keys or res.unexpected_keys:
        raise KeyError(
            f"{p}: state dict does not match DINO ViT (missing {res.missing_keys[:5]}, "
            f"unexpected {res.unexpected_keys[:5]})"
        )
    log.info("DINO ViT (dim %d, depth %d, patch %d) loaded from %s", dim, depth, patch, p)
    return model.eval().requires_grad_(False)


def joint_bilateral_upsample(
    feat: torch.Tensor,
    guide: torch.Tensor,
    radius: int = 2,
    sigma_spatial: float = 1.0,
    sigma_range: float = 0.15,
) -> torch.Tensor:
    """Differentiable joint-bilateral upsampling (Kopf et al. 2007), in place of FeatUp.

    feat: (B, C, h, w) low-res features; guide: (B, 3, H, W) image in [0, 1] with H = s h, W = s w
    (integer s). Each output pixel averages the (2 radius + 1)^2 low-res cells around its own, weighted
    by a spatial Gaussian (sigma_spatial, in low-res cells, between the pixel's position and the cell
    centre) times a range Gaussian (sigma_range) on the colour difference between the pixel and the
    cell's mean colour, so feature edges snap to image edges. Returns (B, C, H, W). Memory stays at the
    output's size: weights are per (pixel, offset), features per (cell, offset).
    """
    B, C, h, w = feat.shape
    H, W = guide.shape[-2:]
    if H % h or W % w or H // h != W // w:
        raise ValueError(f"guide {H}x{W} must be the same integer multiple of the features' {h}x{w}")
    s = H // h
    k = 2 * radius + 1
    low = F.avg_pool2d(guide, s)  # (B, 3, h, w) cell mean colours
    pad = (radius,) * 4
    f_unf = F.unfold(F.pad(feat, pad, mode="replicate"), k).view(B, C, k * k, h, w)
    g_unf = F.unfold(F.pad(low, pad, mode="replicate"), k).view(B, 3, k * k, h, w)
    # sub-cell position of each hi-res pixel, in low-res cell units relative to its cell centre
    o = (torch.arange(s, dtype=feat.dtype) + 0.5) / s - 0.5
    d = torch.arange(-radius, radius + 1, dtype=feat.dtype)
    dy = (o[None, :] - d[:, None]) ** 2  # (k, s)
    sp = torch.exp(-(dy[:, None, :, None] + dy[None, :, None, :]) / (2 * sigma_spatial**2))  # (k,k,s,s)
    sp = sp.reshape(k * k, 1, s, 1, s)  # (K, h, s, w, s) broadcast
    gi = guide.view(B, 3, 1, h, s, w, s)
    diff = ((gi - g_unf[:, :, :, :, None, :, None]) ** 2).sum(1)  # (B, K, h, s, w, s)
    wgt = sp[None] * torch.exp(-diff / (2 * sigma_range**2))
    wgt = wgt / wgt.sum(1, keepdim=True).clamp_min(1e-12)
    out = torch.einsum("bkhiwj,bckhw->bchiwj", wgt, f_unf)
    return out.reshape(B, C, H, W)


class DinoFeatures(nn.Module):
    """DINO ViT-S/16 patch tokens, L2-normalised, joint-bilateral-upsampled to the image size.

    forward: (B, 3, H, W) in [0, 1] (H, W multiples of 16; the paper uses 256x256) -> (B, 384, H, W).
    """

    name = DINO_NAME

    def __init__(self, vit: DinoViT, radius: int = 2, sigma_spatial: float = 1.0, sigma_range: float = 0.15):
        super().__init__()
        self.vit = vit
        self.kw = {"radius": radius, "sigma_spatial": sigma_spatial, "sigma_range": sigma_range}

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        f = F.normalize(self.vit(img), dim=1)
        return joint_bilateral_upsample(f, img, **self.kw)


# ----------------------------------------------------------------------------------------------------
# analytic default


@dataclass(frozen=True)
class AnalyticFeatureConfig:
    """sigmas: derivative-of-Gaussian scales in pixels. n_orient: orientations in [0, pi).
    norm_sigma: Gaussian window (pixels) of the local energy normalisation. eps: floor of the local
    energy, relative to an image in [0, 1]; keeps flat regions at ~0 instead of amplifying noise."""

    sigmas: tuple[float, ...] = (1.0, 2.0, 4.0)
    n_orient: int = 4
    norm_sigma: float = 6.0
    eps: float = 1e-6


def _gauss_kernels(sigma: float, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r = int(math.ceil(3.5 * sigma))
    x = torch.arange(-r, r + 1, dtype=dtype)
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1 / sigma**2) * g
    g2 = g2 - g2.mean()  # exact zero response to constants
    return g, g1, g2


def _sep(x: torch.Tensor, ky: torch.Tensor, kx: torch.Tensor) -> torch.Tensor:
    r = (ky.numel() - 1) // 2
    x = F.pad(x, (r, r, r, r), mode="reflect")
    x = F.conv2d(x, ky.view(1, 1, -1, 1))
    return F.conv2d(x, kx.view(1, 1, 1, -1))


class AnalyticFeatures(nn.Module):
    """The embedded structure descriptor (see module docstring).

    forward: (B, 3, H, W) in [0, 1] -> (B, 2 n_orient len(sigmas), H, W) float (same dtype), ~unit RMS
    where the image has structure. H, W > 3.5 max(sigmas) (reflect padding).
    """

    name = ANALYTIC_NAME

    def __init__(self, cfg: AnalyticFeatureConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or AnalyticFeatureConfig()

    @property
    def channels(self) -> int:
        return 2 * self.cfg.n_orient * len(self.cfg.sigmas)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        c = self.cfg
        lum = 0.299 * img[:, 0:1] + 0.587 * img[:, 1:2] + 0.114 * img[:, 2:3]
        th = torch.arange(c.n_orient, dtype=img.dtype) * math.pi / c.n_orient
        co, si = th.cos().view(1, -1, 1, 1), th.sin().view(1, -1, 1, 1)
        out = []
        for s in c.sigmas:
            g, g1, g2 = _gauss_kernels(s, img.dtype)
            gx, gy = _sep(lum, g, g1), _sep(lum, g1, g)
            gxx, gyy, gxy = _sep(lum, g, g2), _sep(lum, g2, g), _sep(lum, g1, g1)
            # steerable filters: any orientation from the x/y basis; scale-normalised (s, s^2)
            out.append(s * (co * gx + si * gy))
            out.append(s * s * (co * co * gxx + 2 * co * si * gxy + si * si * gyy))
        r = torch.cat(out, dim=1)
        g, _, _ = _gauss_kernels(c.norm_sigma, img.dtype)
        energy = _sep(r.pow(2).mean(1, keepdim=True), g, g)
        return r / torch.sqrt(energy + c.eps)


def make_feature_extractor(dino_path: str | os.PathLike | None = None) -> tuple[Callable, str]:
    """(extractor, name): DINO + joint-bilateral upsampling when weights are given (argument or
    $COIN_DINO_WEIGHTS), else the analytic default; the choice is logged."""
    if dino_path is not None or os.environ.get(DINO_ENV):
        ext = DinoFeatures(load_dino(dino_path))
        log.info("features: %s", DINO_NAME)
        return ext, DINO_NAME
    log.info("features: no DINO weights (%s unset), using the %s", DINO_ENV, ANALYTIC_NAME)
    return AnalyticFeatures(), ANALYTIC_NAME
