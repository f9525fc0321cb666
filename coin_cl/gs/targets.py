"""Ref-GS training targets (CoIn paper 4.2 and 5.1): the inpaint I^_n inside the mask, the
captured image outside it."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.scene.masks import mask_of_shape


def composite_targets(inpainted: Any, image: Any, mask: Any) -> Any:
    """The Ref-GS target: the inpaint I^_n inside the mask, the captured image outside.

    The inpainter may alter pixels it was not asked to change (colour shifts, VAE round trips);
    the captured pixels outside the mask are ground truth, so they win (paper 5.1).

    Args:
        inpainted, image: [H, W, 3] float, both numpy or both torch.
        mask: [H, W] bool, True = region to inpaint.
    Returns:
        [H, W, 3], same type and dtype as `inpainted`.
    """
    if tuple(inpainted.shape) != tuple(image.shape) or inpainted.ndim != 3:
        raise ValueError(
            f"inpainted {tuple(inpainted.shape)} and image {tuple(image.shape)} must both be [H, W, C]"
        )
    H, W = inpainted.shape[:2]
    if isinstance(inpainted, Tensor):
        m = torch.as_tensor(mask_of_shape(mask, H, W, "composite_targets"), device=inpainted.device)
        return torch.where(m[..., None], inpainted, image.to(inpainted.dtype))
    m = mask_of_shape(mask, H, W, "composite_targets")
    return np.where(m[..., None], inpainted, np.asarray(image, dtype=np.asarray(inpainted).dtype))
