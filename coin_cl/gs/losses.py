"""Photometric loss (1 - lambda) * L1 + lambda * (1 - SSIM) with per-view weights and pixel masks.

Masked pixels are *excluded*: both the prediction and the target are set to a neutral constant
there before either term is computed, so those pixels get an exactly-zero gradient and neither
image's content inside the mask can leak in through the SSIM windows of neighbouring pixels;
both means run over the kept pixels only. A per-view weight multiplies that view's loss, so
weight 0 removes the view.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True)
class LossConfig:
    lambda_dssim: float = 0.2  # paper eq. 2 / 3DGS
    ssim_window: int = 11
    ssim_sigma: float = 1.5
    ssim_c1: float = 0.01**2
    ssim_c2: float = 0.03**2


MASK_FILL = 0.5  # value both images take inside an exclusion mask (any constant would do)


def ssim_map(a: Tensor, b: Tensor, cfg: LossConfig = LossConfig(), backend: str = "torch",
             device: Any = None) -> Tensor:  # fmt: skip
    """Per-pixel SSIM (Gaussian window, zero padding like 3DGS' training loss).

    Args:
        a, b: [B, H, W, C] images in [0, 1]. backend: "torch" (`coin_cl.engine.reference.ssim_map`)
            or "opencl" (the fused kernel, gradient to `a` only); device: its OpenCL device.
    Returns:
        [B, H, W] SSIM averaged over channels.
    """
    from coin_cl.engine import ssim_map as engine_ssim

    return engine_ssim(a, b, cfg.ssim_window, cfg.ssim_sigma, cfg.ssim_c1, cfg.ssim_c2, backend=backend,
                       device=device)  # fmt: skip


def photometric_map(
    pred: Tensor,
    target: Tensor,
    exclude: Tensor | None = None,
    cfg: LossConfig = LossConfig(),
    backend: str = "torch",
    device: Any = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Each pixel's share of its view's (1 - lambda) L1 + lambda (1 - SSIM), the mean over the
    kept pixels: [B, H, W] images' map sums to the per-view loss, 0 at excluded pixels (a view with
    every pixel excluded has loss 0).

    Returns:
        (map [B, H, W], parts with per-view 'l1', 'ssim', 'loss' [B], detached).
    """
    b = pred.shape[0]
    target = target.to(pred.dtype)
    if exclude is not None:
        keep = (~exclude.bool()).to(pred.dtype)
        ex = exclude.bool()[..., None]
        pred = torch.where(ex, torch.full_like(pred, MASK_FILL), pred)
        target = torch.where(ex, torch.full_like(target, MASK_FILL), target)
        n_keep = keep.sum((1, 2))
    else:
        keep = torch.ones(pred.shape[:3], dtype=pred.dtype)
        n_keep = pred.new_full((b,), float(pred.shape[1] * pred.shape[2]))
    l1_px = (pred - target).abs().mean(-1) * keep
    s_px = ssim_map(pred, target, cfg, backend, device) * keep
    denom = n_keep.clamp_min(1.0)[:, None, None]
    px = ((1 - cfg.lambda_dssim) * l1_px + cfg.lambda_dssim * (keep - s_px)) / denom
    parts = {"l1": (l1_px / denom).sum((1, 2)), "ssim": (s_px / denom).sum((1, 2)), "loss": px.sum((1, 2))}
    return px, {k: v.detach() for k, v in parts.items()}


def photometric_loss(
    pred: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    exclude: Tensor | None = None,
    cfg: LossConfig = LossConfig(),
    backend: str = "torch",
    device: Any = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted, masked (1 - lambda) L1 + lambda (1 - SSIM), summed over views.

    Args:
        pred, target: [B, H, W, C] (or [H, W, C] for one view).
        weights: [B] per-view weights (default ones); weight 0 => that view contributes nothing.
        exclude: [B, H, W] bool, True = pixel left out of the loss (e.g. the masked object).
        backend, device: where the SSIM term runs (`ssim_map`); "opencl" needs a target that
            does not require a gradient.
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
    px, parts = photometric_map(pred, target, exclude, cfg, backend, device)
    per_view = px.sum((1, 2))
    # A zero weight must give an exactly zero gradient even if the view's loss is not finite.
    weighted = torch.where(weights != 0, weights * per_view, torch.zeros_like(per_view))
    return weighted.sum(), parts
