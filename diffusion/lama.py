"""LaMa (Suvorov et al. 2022) from a local TorchScript file: the ``big-lama.pt`` that IOPaint /
lama-cleaner users already have (never downloaded). SPIn-NeRF made the shared scene's per-view
inpaints with LaMa; this is the paper's initial 2D inpaint (section 4.1) with that model.

Calling convention of that file (as IOPaint / lama-cleaner call it): ``model(image, mask)`` with
image (1, 3, H, W) float32 RGB in [0, 1] and mask (1, 1, H, W) float32 in {0, 1} (1 = fill); H and W
padded up to a multiple of 8 by symmetric (mirror) padding at the bottom and right; the output is
(1, 3, H, W) RGB in [0, 1], cropped back to the input size. The file is named by an argument or the
``COIN_LAMA_PATH`` environment variable (the CLI's ``--lama-path``).

A TorchScript file is a program, not data: loading it and calling it runs the code it holds, and
nothing here sandboxes that. The LaMa file is trusted input, like an executable: name only a file
from a source you trust (IOPaint's big-lama.pt). Checkpoints, by contrast, are read without running
anything (`coin_cl.checkpoint`).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch

from .inpaint2d import check_image_mask

log = logging.getLogger(__name__)

LAMA_ENV = "COIN_LAMA_PATH"
LAMA_NAME = "LaMa (TorchScript)"
PAD_MOD = 8


def resolve_lama_path(path: str | os.PathLike | None = None) -> Path:
    """The LaMa file from the argument, else ``$COIN_LAMA_PATH``; FileNotFoundError naming both when
    neither gives an existing file."""
    src = "--lama-path / lama_path" if path is not None else LAMA_ENV
    p = path if path is not None else os.environ.get(LAMA_ENV)
    if not p:
        raise FileNotFoundError(
            f"no LaMa model given: set {LAMA_ENV} (or pass --lama-path) to the TorchScript big-lama.pt "
            "that IOPaint / lama-cleaner use (nothing is downloaded)"
        )
    p = Path(p)
    if not p.is_file():
        raise FileNotFoundError(f"LaMa model {p} ({src}) does not exist: set {LAMA_ENV} to big-lama.pt")
    return p


def load_lama(path: str | os.PathLike | None = None) -> torch.jit.ScriptModule:
    """Load the TorchScript LaMa on the CPU (eval mode); a file that is not a TorchScript archive
    gives a ValueError naming it and COIN_LAMA_PATH. The file runs as code: trusted input only."""
    p = resolve_lama_path(path)
    try:
        model = torch.jit.load(str(p), map_location="cpu")
    except (RuntimeError, ValueError) as e:
        raise ValueError(
            f"{p} is not a TorchScript LaMa model (torch.jit.load failed: {str(e).splitlines()[0]}); "
            f"set {LAMA_ENV} to IOPaint's big-lama.pt"
        ) from None
    model.eval()
    return model


def _pad_to(a: np.ndarray, mod: int) -> np.ndarray:
    """(H, W, C) padded at the bottom/right by mirroring up to multiples of mod."""
    H, W = a.shape[:2]
    ph, pw = (-H) % mod, (-W) % mod
    return np.pad(a, ((0, ph), (0, pw), (0, 0)), mode="symmetric") if ph or pw else a


def lama_inpaint(model, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Inpaint (H, W, 3) float [0, 1] `image` under (H, W) bool `mask` with a loaded LaMa module.
    Returns the full model output (H, W, 3) float32 in [0, 1] (the caller pastes it in the mask).
    A wrong output shape or non-finite values raise ValueError."""
    image, mask = check_image_mask(image, mask)
    H, W = mask.shape
    img = _pad_to(image, PAD_MOD)
    m = _pad_to(mask[..., None].astype(np.float32), PAD_MOD)
    it = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
    mt = torch.from_numpy(np.ascontiguousarray(m.transpose(2, 0, 1)))[None]
    with torch.inference_mode():
        out = model(it, mt)
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != tuple(it.shape):
        got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ValueError(f"LaMa returned {got}, expected {tuple(it.shape)}: is {LAMA_ENV} big-lama.pt?")
    res = out[0, :, :H, :W].permute(1, 2, 0).float().numpy()
    if not np.isfinite(res).all():
        raise ValueError("LaMa returned NaN/Inf")
    return np.clip(res, 0, 1).astype(np.float32)
