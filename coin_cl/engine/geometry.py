"""Small math shared by the fast path and the float64 twins (so neither imports the other)."""

from __future__ import annotations

import torch
from torch import Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: [..., 4] (w, x, y, z), any non-zero norm (normalised here).
    Returns:
        [..., 3, 3]
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def finite_rows(*tensors: Tensor) -> Tensor:
    """[N] bool: rows where every given [N, ...] tensor is finite."""
    ok = torch.ones(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    # Fast path: a sum containing NaN or Inf is not finite, so a finite total proves every entry
    # finite (one read of each tensor instead of isfinite + all per row); a total that overflows
    # merely falls through to the exact per-row test.
    with torch.no_grad():
        if all(bool(torch.isfinite(t.detach().sum())) for t in tensors):
            return ok
    for t in tensors:
        t = t[:, None] if t.dim() == 1 else t.flatten(1)
        ok = ok & torch.isfinite(t).all(dim=1)
    return ok


def gaussian_window(window: int, sigma: float) -> Tensor:
    """[window] float64 normalised 1D Gaussian weights of the SSIM window."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"SSIM window must be a positive odd width, got {window}")
    if not sigma > 0:
        raise ValueError(f"SSIM sigma must be positive, got {sigma}")
    x = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def check_ssim_inputs(a: Tensor, b: Tensor) -> None:
    """Two [B, H, W, C] images of one shape, else a clear error."""
    if a.dim() != 4 or a.shape != b.shape:
        raise ValueError(
            f"ssim_map takes two [B, H, W, C] images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}"
        )
