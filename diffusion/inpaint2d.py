"""Initial 2D inpainting (paper 4.1): mask-centred square crops, inpaint, resize back, paste in the mask.

Sources, in order of preference (the first one given is used, and its name is returned and logged):
1. "Stable Diffusion 2 inpainting" (an :class:`~.sd2.SD2Denoiser`), on 512x512 crops as the paper;
2. "dataset per-view inpaint" (the scene's own inpaints, e.g. SPIn-NeRF's ``RGB_inpainted/``, passed
   in by the caller as an image of the same size);
3. "scene prior" (a :class:`~.scene_prior.ScenePrior`), on crops of its own working size;
4. "OpenCV classical inpainting (<method>)", the last resort.

Images are (H, W, 3) float32 in [0, 1]; masks (H, W) bool, True = to fill. Pixels outside the mask are
bit-identical to the input. The paste is "slightly feathered" inside the mask: the fill's weight is 1
deeper than ``feather_px`` pixels from the mask's edge and ramps down to 0.5 on its outermost ring
(there the result is the mean of the fill and the input). This hides the small colour offset of a
generated crop; it assumes, as SPIn-NeRF's masks are, that the mask is dilated a little beyond the
object. ``feather_px = 0`` gives a hard paste.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch

from coin_cl.crop import crop_image, resize_to  # numpy and OpenCV only: no engine, no pipeline

from .sampling import EnergyFn, SamplerConfig

log = logging.getLogger(__name__)

SD2_NAME = "Stable Diffusion 2 inpainting"
DATASET_NAME = "dataset per-view inpaint"
PRIOR_NAME = "scene prior"
FSR_BLOCK = 32  # OpenCV xphoto FSR's block grid (16 px) times 2: images are padded to a multiple of it


@dataclass
class InpaintConfig:
    """sd_crop: crop size for SD2 (paper: 512). context: the crop side is at least context x the mask's
    bounding-box side, so the model sees surroundings. feather_px: paste feather width inside the mask.
    opencv_method: 'telea', 'ns', 'fsr_fast' or 'fsr_best'. opencv_radius: radius of telea/ns.
    sampler_sd / sampler_prior: DDIM settings (paper: 50 'uniform' steps; the scene prior's fills
    measured sharper with eta = 0 than eta = 1 on the test texture)."""

    sd_crop: int = 512
    context: float = 1.5
    feather_px: int = 2
    opencv_method: str = "telea"
    opencv_radius: int = 5
    sampler_sd: SamplerConfig = field(
        default_factory=lambda: SamplerConfig(num_steps=50, discretization="uniform", cfg_scale=7.5)
    )
    sampler_prior: SamplerConfig = field(
        default_factory=lambda: SamplerConfig(num_steps=50, discretization="uniform", eta=0.0)
    )


def check_image_mask(image: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate (H, W, 3) float image and (H, W) mask; returns (float32 image, bool mask)."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) float in [0, 1], got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"image must be float in [0, 1] (divide uint8 by 255), got dtype {image.dtype}")
    if not np.isfinite(image).all():
        raise ValueError(
            f"image contains {int((~np.isfinite(image)).sum())} NaN/Inf values: "
            "fix the input image before inpainting"
        )
    mask = np.asarray(mask)
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask shape {mask.shape} does not match the image's {image.shape[:2]}")
    return image.astype(np.float32, copy=False), mask.astype(bool)


def crop_box(mask: np.ndarray, min_side: int, context: float) -> tuple[int, int, int]:
    """Square crop (y0, x0, side) centred on the mask's bounding box, side >= min_side and >= context x
    the box side; kept inside the image when it fits (y0/x0 may be negative, or the crop reach past the
    far border, when side exceeds the image: the crop is then padded by reflection)."""
    H, W = mask.shape
    ys, xs = np.nonzero(mask)
    y1, y2, x1, x2 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    side = max(min_side, int(math.ceil(context * max(y2 - y1, x2 - x1))))
    cy, cx = (y1 + y2) / 2, (x1 + x2) / 2

    def place(c: float, n: int) -> int:
        s0 = int(round(c - side / 2))
        if side <= n:
            return min(max(s0, 0), n - side)
        return -((side - n) // 2)  # centre the image in an oversized crop

    return place(cy, H), place(cx, W), side


def feather_weights(mask: np.ndarray, feather_px: int) -> np.ndarray:
    """Paste weights (H, W) float32: 0 outside the mask, 0.5 on its outer ring, 1 deeper than feather_px."""
    if feather_px <= 0:
        return mask.astype(np.float32)
    d = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)  # >= 1 inside the mask
    return np.where(mask, np.clip(0.5 + 0.5 * (d - 1) / feather_px, 0.5, 1.0), 0.0).astype(np.float32)


# What a paste's feather blends the fill with on the mask's outer rings (`paste`).
PASTE_EDGES = ("image", "surroundings")


def paste(
    image: np.ndarray, fill: np.ndarray, mask: np.ndarray, feather_px: int, edge: str = "image"
) -> np.ndarray:
    """image outside the mask (bit-identical), feathered blend of fill and `edge` inside it.

    edge: "image" blends with the image's own pixels under the mask's outer rings, for masks dilated
    beyond the object (those pixels are background) or an image whose masked pixels are already a
    fill; "surroundings" blends with the pixels outside the mask continued inward (OpenCV's Telea),
    for exact masks, whose outer ring is the object itself: blended with it, the object's colours
    would stay as an outline."""
    if edge not in PASTE_EDGES:
        raise ValueError(f"paste edge must be one of {', '.join(PASTE_EDGES)}, got {edge!r}")
    w = feather_weights(mask, feather_px)[..., None]
    under = image
    if edge == "surroundings" and feather_px > 0 and mask.any() and not mask.all():
        under = opencv_inpaint(image, mask, "telea", radius=feather_px + 1)
    blend = (w * fill + (1 - w) * under).astype(np.float32)
    return np.where(mask[..., None], blend, image)


def opencv_inpaint(image: np.ndarray, mask: np.ndarray, method: str = "telea", radius: int = 5) -> np.ndarray:
    """OpenCV classical inpainting of (H, W, 3) float [0, 1] under (H, W) bool; returns the full image."""
    u8 = np.clip(np.round(image * 255), 0, 255).astype(np.uint8)
    m8 = mask.astype(np.uint8) * 255
    if method in ("telea", "ns"):
        flag = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
        out = cv2.inpaint(u8, m8, radius, flag)  # cv2.inpaint: mask non-zero = fill
    elif method in ("fsr_fast", "fsr_best"):
        # FSR works on 16-px blocks and leaves the last (H mod 16) rows / (W mod 16) columns of a hole
        # unreconstructed, at its YCrCb zero: RGB (0, 135, 0) in the fill. The image and the mask are
        # therefore mirrored out to a multiple of FSR_BLOCK (the mirrored hole stays a hole) and cropped.
        H, W = m8.shape
        pad = ((0, -H % FSR_BLOCK), (0, -W % FSR_BLOCK))
        u8p = np.pad(u8, pad + ((0, 0),), mode="symmetric")
        m8p = np.pad(m8, pad, mode="symmetric")
        out = np.zeros_like(u8p)
        flag = cv2.xphoto.INPAINT_FSR_FAST if method == "fsr_fast" else cv2.xphoto.INPAINT_FSR_BEST
        cv2.xphoto.inpaint(u8p, 255 - m8p, out, flag)  # xphoto: mask non-zero = VALID
        out = out[:H, :W]
    else:
        raise ValueError(f"opencv_method must be telea, ns, fsr_fast or fsr_best, got {method!r}")
    return out.astype(np.float32) / 255.0


def _model_fill(
    model: Any,
    image: np.ndarray,
    mask: np.ndarray,
    size: int,
    cfg: InpaintConfig,
    sampler: SamplerConfig,
    prompt: str,
    seed: int,
    energy: EnergyFn | None,
) -> np.ndarray:
    """Crop, resize to the model's size, sample, resize back; returns a full-size fill (H, W, 3)."""
    H, W = mask.shape
    y0, x0, side = crop_box(mask, size, cfg.context)
    ci, cm = crop_image(image, y0, x0, side, side), crop_image(mask, y0, x0, side, side)
    if cm.all():
        raise ValueError("the crop around the mask is entirely masked: nothing to condition on")
    ri = resize_to(ci, size, size)
    # any coverage of a low-res pixel makes it a hole, so thin mask parts are not lost by downscaling
    rm = cv2.resize(cm.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) > 0
    it = torch.from_numpy(np.ascontiguousarray(ri.transpose(2, 0, 1)))[None].float()
    mt = torch.from_numpy(rm.astype(np.float32))[None, None]
    g = torch.Generator().manual_seed(seed)
    out = model.inpaint(it, mt, prompt=prompt, cfg=sampler, energy=energy, generator=g)
    fill = out[0].detach().permute(1, 2, 0).numpy().astype(np.float32)
    back = resize_to(fill, side, side)
    full = image.copy()
    ys, xs = slice(max(y0, 0), min(y0 + side, H)), slice(max(x0, 0), min(x0 + side, W))
    full[ys, xs] = back[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0]
    return np.clip(full, 0, 1)


def inpaint_image(
    image: np.ndarray,
    mask: np.ndarray,
    *,
    sd2: Any = None,
    dataset_inpaint: np.ndarray | None = None,
    scene_prior: Any = None,
    cfg: InpaintConfig | None = None,
    prompt: str = "",
    seed: int = 0,
    energy: EnergyFn | None = None,
    edge: str = "image",
) -> tuple[np.ndarray, str]:
    """Inpaint one view with the first available source (see module docstring); the fill is pasted
    with `paste`'s `edge` ("surroundings" for exact masks).

    image: (H, W, 3) float in [0, 1]; mask: (H, W) bool (True = fill); dataset_inpaint: (H, W, 3)
    float [0, 1] per-view inpaint shipped with the dataset. Returns (image (H, W, 3) float32, source
    name). Empty mask: the input is returned unchanged (source 'none (empty mask)'). A mask covering the
    whole image raises ValueError (nothing to condition on).
    """
    cfg = cfg or InpaintConfig()
    image, mask = check_image_mask(image, mask)
    if not mask.any():
        log.info("inpaint: empty mask, returning the input unchanged")
        return image.copy(), "none (empty mask)"
    if mask.all():
        raise ValueError("mask covers the whole image: nothing to condition the inpainting on")
    if sd2 is not None:
        source = SD2_NAME
        fill = _model_fill(sd2, image, mask, cfg.sd_crop, cfg, cfg.sampler_sd, prompt, seed, energy)
    elif dataset_inpaint is not None:
        source = DATASET_NAME
        fill = np.asarray(dataset_inpaint, dtype=np.float32)
        if fill.shape != image.shape:
            raise ValueError(f"dataset inpaint shape {fill.shape} does not match the image's {image.shape}")
        if not np.isfinite(fill).all():
            raise ValueError("dataset inpaint contains NaN/Inf")
        # debug: a pipeline calls this per view and logs the sources once (the return names it)
        log.debug("inpaint: no Stable Diffusion weights, using the %s", DATASET_NAME)
    elif scene_prior is not None:
        source = PRIOR_NAME
        log.debug("inpaint: no Stable Diffusion weights or dataset inpaints, using the %s", PRIOR_NAME)
        fill = _model_fill(
            scene_prior, image, mask, scene_prior.work_size, cfg, cfg.sampler_prior, prompt, seed, energy
        )
    else:
        source = f"OpenCV classical inpainting ({cfg.opencv_method})"
        log.warning("inpaint: no learned source available, falling back to %s", source)
        fill = opencv_inpaint(image, mask, cfg.opencv_method, cfg.opencv_radius)
    return paste(image, fill, mask, cfg.feather_px, edge), source
