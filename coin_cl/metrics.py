"""Image-quality metrics for inpainted views: full-image and masked (paper section 5, supp. B).

- PSNR, SSIM (scikit-image, Gaussian window sigma 1.5, population covariance, as 3DGS papers report);
- m-PSNR: PSNR of the pixels inside the ground-truth mask; m-SSIM: the SSIM map averaged inside it;
- bbox-PSNR / bbox-SSIM / m-LPIPS: the metric on the crop to the mask's bounding box (SPIn-NeRF's
  way of scoring the masked region with a metric that needs a whole image);
- LPIPS (AlexNet or VGG16 backbone + LPIPS linear heads) only from local weight files the user names;
  FID / m-FID (FID of the bounding-box crops) with pytorch-fid's Inception-v3 from a local file.
  Nothing is ever computed with random weights: an unavailable metric is None with a reason.

Images are (H, W, 3) float in [0, 1]; masks (H, W) bool, True = the region to score.
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from skimage.metrics import structural_similarity

log = logging.getLogger(__name__)

SSIM_KW = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
SSIM_MIN_SIDE = 11  # the Gaussian window for sigma 1.5 is 11 x 11 pixels
LPIPS_MIN_SIDE = 32  # AlexNet's first stride-4 conv + pools need a few tens of pixels
FID_ENV = "COIN_FID_WEIGHTS"
FID_UNAVAILABLE = (
    "FID unavailable: set COIN_FID_WEIGHTS to pytorch-fid's pt_inception-2015-12-05-6726825d.pth; "
    "no weights are downloaded"
)


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


def gmsd(pred: np.ndarray, gt: np.ndarray) -> float:
    """Gradient magnitude similarity deviation (Xue et al. 2014; OpenCV's `quality` module) of two
    (H, W, 3) float [0, 1] images: 0 is identical structure, larger is worse. Images are scaled to
    [0, 255] first, the range OpenCV's constant assumes."""
    p, g = _check_pair(pred, gt)
    v, _ = cv2.quality.QualityGMSD_compute((g * 255).astype(np.float64), (p * 255).astype(np.float64))
    return float(v[0])


def bbox_gmsd(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """GMSD on the crop to the mask's bounding box (NaN for an empty mask)."""
    crop = bbox_crop(mask)
    return math.nan if crop is None else gmsd(np.asarray(pred)[crop], np.asarray(gt)[crop])


def _grad_mag(img: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(np.asarray(img, np.float32), cv2.COLOR_RGB2GRAY)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
    return np.sqrt(gx * gx + gy * gy)


def hf_ratio(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, power: int = 1) -> float:
    """High-frequency ratio inside `mask`: mean Sobel gradient magnitude (power=1; power=2: gradient
    energy) of the prediction over that of the ground truth. 1 is right, below 1 is blur (a smear
    where an object was), above 1 is texture stronger than the truth's. NaN for an empty mask or a
    flat ground truth there. What PSNR does not see: a sharp wrong guess and a blur can score the
    same PSNR but not the same ratio."""
    p, g = _check_pair(pred, gt)
    m = np.asarray(mask, bool)
    if not m.any():
        return math.nan
    num = float((_grad_mag(p)[m] ** power).mean())
    den = float((_grad_mag(g)[m] ** power).mean())
    return num / den if den > 0 else math.nan


# ----------------------------------------------------------------------------------------------
# LPIPS in plain torch (torchvision cannot be imported beside the pinned CPU torch).

ALEX_TAPS = (1, 4, 7, 9, 11)  # ReLU outputs after conv1..conv5 in torchvision's alexnet.features
VGG_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 in vgg16.features
LPIPS_ENV = ("COIN_LPIPS_BACKBONE", "COIN_LPIPS_HEADS")


def _features(net: str):
    """torchvision-compatible `features` Sequential (same indices, so its state_dict loads)."""
    from torch import nn

    if net == "alex":
        return (
            nn.Sequential(
                nn.Conv2d(3, 64, 11, 4, 2),
                nn.ReLU(),
                nn.MaxPool2d(3, 2),
                nn.Conv2d(64, 192, 5, 1, 2),
                nn.ReLU(),
                nn.MaxPool2d(3, 2),
                nn.Conv2d(192, 384, 3, 1, 1),
                nn.ReLU(),
                nn.Conv2d(384, 256, 3, 1, 1),
                nn.ReLU(),
                nn.Conv2d(256, 256, 3, 1, 1),
                nn.ReLU(),
                nn.MaxPool2d(3, 2),
            ),
            ALEX_TAPS,
            (64, 192, 384, 256, 256),
        )
    if net == "vgg":
        layers: list = []
        cin = 3
        for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, v, 3, 1, 1), nn.ReLU()]
                cin = v
        return nn.Sequential(*layers), VGG_TAPS, (64, 128, 256, 512, 512)
    raise ValueError(f"unknown LPIPS backbone {net!r}; use 'alex' or 'vgg'")


def _lpips_module():
    import torch
    from torch import nn

    class LPIPS(nn.Module):
        """LPIPS (Zhang et al. 2018): unit-normalised backbone features, squared differences,
        learned 1x1 channel weights, spatial mean, summed over five layers."""

        def __init__(self, net: str = "alex"):
            super().__init__()
            self.net = net
            self.features, self.taps, chans = _features(net)
            self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in chans)
            self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
            self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

        def _taps(self, x):
            out = []
            for i, layer in enumerate(self.features):
                x = layer(x)
                if i in self.taps:
                    out.append(x)
                    if len(out) == len(self.taps):
                        break
            return out

        def forward(self, a, b):
            """a, b: (B, 3, H, W) in [0, 1] -> (B,) distances."""
            a = (a * 2 - 1 - self.shift) / self.scale
            b = (b * 2 - 1 - self.shift) / self.scale
            total = 0
            for lin, fa, fb in zip(self.lins, self._taps(a), self._taps(b), strict=True):
                fa = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
                fb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
                total = total + lin((fa - fb) ** 2).mean(dim=(2, 3))
            return total[:, 0]

    return LPIPS


def _load_state(path: Path) -> dict:
    import torch

    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weight file {path} not found")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"{path} is not a torch state_dict file ({exc})") from exc
    if isinstance(sd, dict) and "state_dict" in sd:
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise ValueError(f"{path} does not hold a state_dict")
    return sd


def load_lpips(backbone: str | Path, heads: str | Path, net: str = "alex"):
    """An LPIPS module from local files: `backbone` is torchvision's alexnet/vgg16 state_dict
    (e.g. alexnet-owt-7be5be79.pth; keys `features.N.weight`), `heads` the LPIPS linear layers
    (e.g. lpips' weights/v0.1/alex.pth; keys `linK.model.1.weight`). Errors name the file."""
    LPIPS = _lpips_module()
    model = LPIPS(net)
    bpath, hpath = Path(backbone), Path(heads)
    sd = _load_state(bpath)
    feats = {k[len("features.") :]: v for k, v in sd.items() if k.startswith("features.")}
    if not feats:  # a bare `features` state_dict
        feats = {k: v for k, v in sd.items() if re.match(r"^\d+\.", k)}
    try:
        model.features.load_state_dict(feats, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{bpath} does not match the {net} backbone ({exc})") from exc
    hd = _load_state(hpath)
    lins = {}
    for k, v in hd.items():
        m = re.match(r"^lin(\d)\..*weight$", k)
        if m:
            lins[f"{m.group(1)}.weight"] = v
    try:
        model.lins.load_state_dict(lins, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{hpath} does not hold the {net} LPIPS heads lin0..lin4 ({exc})") from exc
    return model.eval()


def lpips_from_env(net: str = "alex"):
    """(module, None) when $COIN_LPIPS_BACKBONE and $COIN_LPIPS_HEADS name weight files,
    else (None, reason). Never falls back to random weights."""
    b, h = (os.environ.get(k) for k in LPIPS_ENV)
    if not b or not h:
        return None, (
            "LPIPS unavailable: set COIN_LPIPS_BACKBONE (torchvision alexnet/vgg16 .pth) and "
            "COIN_LPIPS_HEADS (lpips v0.1 alex.pth/vgg.pth); no weights are downloaded"
        )
    net = os.environ.get("COIN_LPIPS_NET", net)
    return load_lpips(b, h, net), None


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
# FID: pytorch-fid's Inception-v3 (the TF FID graph ported to torch), plain torch.


def _inception_module():
    import torch
    import torch.nn.functional as F
    from torch import nn

    class Conv(nn.Module):
        # torchvision's BasicConv2d: conv without bias, BN (eps 1e-3), ReLU; same key names.
        def __init__(self, cin, cout, k, stride=1, padding=0):
            super().__init__()
            self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=padding, bias=False)
            self.bn = nn.BatchNorm2d(cout, eps=0.001)

        def forward(self, x):
            return F.relu(self.bn(self.conv(x)))

    def avg(x):
        # The FID graph averages without the zero padding (count_include_pad=False).
        return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)

    class A(nn.Module):
        def __init__(self, cin, pool):
            super().__init__()
            self.branch1x1 = Conv(cin, 64, 1)
            self.branch5x5_1 = Conv(cin, 48, 1)
            self.branch5x5_2 = Conv(48, 64, 5, padding=2)
            self.branch3x3dbl_1 = Conv(cin, 64, 1)
            self.branch3x3dbl_2 = Conv(64, 96, 3, padding=1)
            self.branch3x3dbl_3 = Conv(96, 96, 3, padding=1)
            self.branch_pool = Conv(cin, pool, 1)

        def forward(self, x):
            b5 = self.branch5x5_2(self.branch5x5_1(x))
            b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
            return torch.cat([self.branch1x1(x), b5, b3, self.branch_pool(avg(x))], 1)

    class B(nn.Module):
        def __init__(self, cin):
            super().__init__()
            self.branch3x3 = Conv(cin, 384, 3, stride=2)
            self.branch3x3dbl_1 = Conv(cin, 64, 1)
            self.branch3x3dbl_2 = Conv(64, 96, 3, padding=1)
            self.branch3x3dbl_3 = Conv(96, 96, 3, stride=2)

        def forward(self, x):
            b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
            return torch.cat([self.branch3x3(x), b3, F.max_pool2d(x, 3, stride=2)], 1)

    class C(nn.Module):
        def __init__(self, cin, c7):
            super().__init__()
            self.branch1x1 = Conv(cin, 192, 1)
            self.branch7x7_1 = Conv(cin, c7, 1)
            self.branch7x7_2 = Conv(c7, c7, (1, 7), padding=(0, 3))
            self.branch7x7_3 = Conv(c7, 192, (7, 1), padding=(3, 0))
            self.branch7x7dbl_1 = Conv(cin, c7, 1)
            self.branch7x7dbl_2 = Conv(c7, c7, (7, 1), padding=(3, 0))
            self.branch7x7dbl_3 = Conv(c7, c7, (1, 7), padding=(0, 3))
            self.branch7x7dbl_4 = Conv(c7, c7, (7, 1), padding=(3, 0))
            self.branch7x7dbl_5 = Conv(c7, 192, (1, 7), padding=(0, 3))
            self.branch_pool = Conv(cin, 192, 1)

        def forward(self, x):
            b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
            d = x
            for i in range(1, 6):
                d = getattr(self, f"branch7x7dbl_{i}")(d)
            return torch.cat([self.branch1x1(x), b7, d, self.branch_pool(avg(x))], 1)

    class D(nn.Module):
        def __init__(self, cin):
            super().__init__()
            self.branch3x3_1 = Conv(cin, 192, 1)
            self.branch3x3_2 = Conv(192, 320, 3, stride=2)
            self.branch7x7x3_1 = Conv(cin, 192, 1)
            self.branch7x7x3_2 = Conv(192, 192, (1, 7), padding=(0, 3))
            self.branch7x7x3_3 = Conv(192, 192, (7, 1), padding=(3, 0))
            self.branch7x7x3_4 = Conv(192, 192, 3, stride=2)

        def forward(self, x):
            b3 = self.branch3x3_2(self.branch3x3_1(x))
            b7 = x
            for i in range(1, 5):
                b7 = getattr(self, f"branch7x7x3_{i}")(b7)
            return torch.cat([b3, b7, F.max_pool2d(x, 3, stride=2)], 1)

    class E(nn.Module):
        def __init__(self, cin, max_pool):
            super().__init__()
            self.max_pool = max_pool  # the last block of the FID graph pools with max, not mean
            self.branch1x1 = Conv(cin, 320, 1)
            self.branch3x3_1 = Conv(cin, 384, 1)
            self.branch3x3_2a = Conv(384, 384, (1, 3), padding=(0, 1))
            self.branch3x3_2b = Conv(384, 384, (3, 1), padding=(1, 0))
            self.branch3x3dbl_1 = Conv(cin, 448, 1)
            self.branch3x3dbl_2 = Conv(448, 384, 3, padding=1)
            self.branch3x3dbl_3a = Conv(384, 384, (1, 3), padding=(0, 1))
            self.branch3x3dbl_3b = Conv(384, 384, (3, 1), padding=(1, 0))
            self.branch_pool = Conv(cin, 192, 1)

        def forward(self, x):
            b3 = self.branch3x3_1(x)
            b3 = torch.cat([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], 1)
            d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
            d = torch.cat([self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d)], 1)
            p = F.max_pool2d(x, 3, stride=1, padding=1) if self.max_pool else avg(x)
            return torch.cat([self.branch1x1(x), b3, d, self.branch_pool(p)], 1)

    class FIDInception(nn.Module):
        """Inception-v3 as in pytorch-fid (keys as torchvision's Inception3); forward gives the
        (B, 2048) pool features of (B, 3, H, W) images in [0, 1], resized to 299 x 299."""

        def __init__(self):
            super().__init__()
            self.Conv2d_1a_3x3 = Conv(3, 32, 3, stride=2)
            self.Conv2d_2a_3x3 = Conv(32, 32, 3)
            self.Conv2d_2b_3x3 = Conv(32, 64, 3, padding=1)
            self.Conv2d_3b_1x1 = Conv(64, 80, 1)
            self.Conv2d_4a_3x3 = Conv(80, 192, 3)
            self.Mixed_5b = A(192, 32)
            self.Mixed_5c = A(256, 64)
            self.Mixed_5d = A(288, 64)
            self.Mixed_6a = B(288)
            self.Mixed_6b = C(768, 128)
            self.Mixed_6c = C(768, 160)
            self.Mixed_6d = C(768, 160)
            self.Mixed_6e = C(768, 192)
            self.Mixed_7a = D(768)
            self.Mixed_7b = E(1280, max_pool=False)
            self.Mixed_7c = E(2048, max_pool=True)
            self.fc = nn.Linear(2048, 1008)  # unused; present so the file's keys all load

        def forward(self, x):
            x = F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False)
            x = 2 * x - 1
            x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
            x = F.max_pool2d(x, 3, stride=2)
            x = F.max_pool2d(self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x)), 3, stride=2)
            for name in ("5b", "5c", "5d", "6a", "6b", "6c", "6d", "6e", "7a", "7b", "7c"):
                x = getattr(self, f"Mixed_{name}")(x)
            return x.mean(dim=(2, 3))

    return FIDInception


def load_inception(path: str | Path):
    """pytorch-fid's Inception-v3 from a local state_dict file; errors name the file."""
    model = _inception_module()()
    path = Path(path)
    sd = _load_state(path)
    sd = {k: v for k, v in sd.items() if not k.startswith("AuxLogits.")}
    missing, unexpected = model.load_state_dict(sd, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(
            f"{path} does not match pytorch-fid's Inception-v3 (missing {missing[:3]}, "
            f"unexpected {unexpected[:3]}); use pt_inception-2015-12-05-6726825d.pth"
        )
    return model.eval()


def inception_from_env():
    """(module, None) when $COIN_FID_WEIGHTS names a file, else (None, reason)."""
    p = os.environ.get(FID_ENV)
    if not p:
        return None, FID_UNAVAILABLE
    return load_inception(p), None


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
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None, lpips_model=None
) -> dict[str, float | None]:
    """All metrics of one view: psnr, ssim, m_psnr, m_ssim, bbox_psnr, bbox_ssim, hf_ratio (in the
    mask), bbox_gmsd, lpips, m_lpips (None when LPIPS is unavailable; NaN masked metrics for an
    empty or absent mask)."""
    out: dict[str, float | None] = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    m = np.zeros(gt.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    out["m_psnr"] = masked_psnr(pred, gt, m)
    out["m_ssim"] = masked_ssim(pred, gt, m)
    out.update(bbox_metrics(pred, gt, m))
    out["hf_ratio"] = hf_ratio(pred, gt, m)
    out["bbox_gmsd"] = bbox_gmsd(pred, gt, m)
    if lpips_model is None:
        out["lpips"] = out["m_lpips"] = None
    else:
        out["lpips"] = lpips(lpips_model, pred, gt)
        crop = bbox_crop(m, min_side=LPIPS_MIN_SIDE)
        out["m_lpips"] = math.nan if crop is None else lpips(lpips_model, pred[crop], gt[crop])
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
