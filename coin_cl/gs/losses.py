"""Photometric loss (1 - lambda) * L1 + lambda * (1 - SSIM) with per-view weights and pixel masks.

Masked pixels are *excluded*: both the prediction and the target are set to a neutral constant
there before either term is computed, so those pixels get an exactly-zero gradient and neither
image's content inside the mask can leak in through the SSIM windows of neighbouring pixels;
both means run over the kept pixels only. A per-view weight multiplies that view's loss, so
weight 0 removes the view.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class LossConfig:
    lambda_dssim: float = 0.2  # paper eq. 2 / 3DGS
    ssim_window: int = 11
    ssim_sigma: float = 1.5
    ssim_c1: float = 0.01**2
    ssim_c2: float = 0.03**2


MASK_FILL = 0.5  # value both images take inside an exclusion mask (any constant would do)

_WINDOWS: dict[tuple, Tensor] = {}


def _gauss_1d(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    key = (size, sigma, dtype)
    if key not in _WINDOWS:
        x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
        g = torch.exp(-(x**2) / (2 * sigma**2))
        _WINDOWS[key] = (g / g.sum()).to(dtype)
    return _WINDOWS[key]


def _blur(x: Tensor, g: Tensor) -> Tensor:
    """Separable Gaussian filter, 'valid' padding as in 3DGS (which zero-pads; we do not)."""
    c = x.shape[1]
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


def ssim_map(a: Tensor, b: Tensor, cfg: LossConfig = LossConfig()) -> Tensor:
    """Per-pixel SSIM (Gaussian window, zero padding like 3DGS' training loss).

    Args:
        a, b: [B, H, W, C] images in [0, 1].
    Returns:
        [B, H, W] SSIM averaged over channels.
    """
    g = _gauss_1d(cfg.ssim_window, cfg.ssim_sigma, a.dtype)
    pad = cfg.ssim_window // 2
    x = F.pad(a.permute(0, 3, 1, 2), (pad, pad, pad, pad))
    y = F.pad(b.permute(0, 3, 1, 2), (pad, pad, pad, pad))
    c = x.shape[1]
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g)
    mu_x, mu_y, sxx, syy, sxy = stats.split(c, 1)
    mu_xy = mu_x * mu_y
    mu_xx, mu_yy = mu_x * mu_x, mu_y * mu_y
    num = (2 * mu_xy + cfg.ssim_c1) * (2 * (sxy - mu_xy) + cfg.ssim_c2)
    den = (mu_xx + mu_yy + cfg.ssim_c1) * ((sxx - mu_xx) + (syy - mu_yy) + cfg.ssim_c2)
    return (num / den).mean(1)


def photometric_loss(
    pred: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    exclude: Tensor | None = None,
    cfg: LossConfig = LossConfig(),
) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted, masked (1 - lambda) L1 + lambda (1 - SSIM), summed over views.

    Args:
        pred, target: [B, H, W, C] (or [H, W, C] for one view).
        weights: [B] per-view weights (default ones); weight 0 => that view contributes nothing.
        exclude: [B, H, W] bool, True = pixel left out of the loss (e.g. the masked object).
    Returns:
        (loss scalar = sum_b w_b * L_b, parts with per-view 'l1' [B], 'ssim' [B], 'loss' [B]).
    """
    if pred.dim() == 3:
        pred, target = pred[None], target[None]
        exclude = None if exclude is None else exclude[None]
    b = pred.shape[0]
    if weights is None:
        weights = pred.new_ones(b)
    weights = torch.as_tensor(weights, dtype=pred.dtype)
    target = target.to(pred.dtype)
    if exclude is not None:
        keep = (~exclude.bool()).to(pred.dtype)
        ex = exclude.bool()[..., None]
        pred = torch.where(ex, torch.full_like(pred, MASK_FILL), pred)
        target = torch.where(ex, torch.full_like(target, MASK_FILL), target)
        n_keep = keep.sum((1, 2))
    else:
        keep = None
        n_keep = pred.new_full((b,), float(pred.shape[1] * pred.shape[2]))
    l1_px = (pred - target).abs().mean(-1)
    s_px = ssim_map(pred, target, cfg)
    if keep is not None:
        l1_px, s_px = l1_px * keep, s_px * keep
    l1 = l1_px.sum((1, 2)) / n_keep.clamp_min(1.0)
    ssim = s_px.sum((1, 2)) / n_keep.clamp_min(1.0)
    per_view = (1 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (1 - ssim)
    per_view = torch.where(n_keep > 0, per_view, torch.zeros_like(per_view))  # all pixels excluded
    # A zero weight must give an exactly zero gradient even if the view's loss is not finite.
    weighted = torch.where(weights != 0, weights * per_view, torch.zeros_like(per_view))
    return weighted.sum(), {"l1": l1.detach(), "ssim": ssim.detach(), "loss": per_view.detach()}
