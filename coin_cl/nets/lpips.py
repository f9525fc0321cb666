"""LPIPS (Zhang et al. 2018) in plain torch: AlexNet / VGG16 feature backbones with torchvision's
layer indices (so torchvision's state_dicts load) and the LPIPS linear heads. torchvision cannot be
imported beside the pinned CPU torch, hence the re-implementation. Weights: `coin_cl.nets.weights`."""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch
from torch import nn

from .weights import WeightFile, load_state_dict, unavailable

ALEX_TAPS = (1, 4, 7, 9, 11)  # ReLU outputs after conv1..conv5 in torchvision's alexnet.features
VGG_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 in vgg16.features
BACKBONE = WeightFile("COIN_LPIPS_BACKBONE", "torchvision's alexnet/vgg16 state_dict (.pth)")
HEADS = WeightFile("COIN_LPIPS_HEADS", "lpips' v0.1 alex.pth/vgg.pth")
LPIPS_ENV = (BACKBONE.env, HEADS.env)
NET_ENV = "COIN_LPIPS_NET"  # "alex" (default) or "vgg"


def backbone(net: str) -> tuple[nn.Sequential, tuple[int, ...], tuple[int, ...]]:
    """torchvision-compatible `features` Sequential (same indices, so its state_dict loads), the
    indices of the five tapped ReLUs and their channel counts."""
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


class LPIPS(nn.Module):
    """LPIPS: unit-normalised backbone features, squared differences, learned 1x1 channel weights,
    spatial mean, summed over five layers."""

    def __init__(self, net: str = "alex"):
        super().__init__()
        self.net = net
        self.features, self.taps, chans = backbone(net)
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


def load_lpips(backbone_file: str | Path, heads_file: str | Path, net: str = "alex") -> LPIPS:
    """An LPIPS module from local files: `backbone_file` is torchvision's alexnet/vgg16 state_dict
    (e.g. alexnet-owt-7be5be79.pth; keys `features.N.weight`), `heads_file` the LPIPS linear layers
    (e.g. lpips' weights/v0.1/alex.pth; keys `linK.model.1.weight`). Errors name the file."""
    model = LPIPS(net)
    bpath, hpath = Path(backbone_file), Path(heads_file)
    sd = load_state_dict(bpath, "LPIPS weight file")
    feats = {k[len("features.") :]: v for k, v in sd.items() if k.startswith("features.")}
    if not feats:  # a bare `features` state_dict
        feats = {k: v for k, v in sd.items() if re.match(r"^\d+\.", k)}
    try:
        model.features.load_state_dict(feats, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{bpath} does not match the {net} backbone ({exc})") from exc
    hd = load_state_dict(hpath, "LPIPS weight file")
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


def lpips_from_env(net: str = "alex") -> tuple[LPIPS | None, str | None]:
    """(module, None) when $COIN_LPIPS_BACKBONE and $COIN_LPIPS_HEADS name weight files, else
    (None, reason); $COIN_LPIPS_NET overrides `net`. Never falls back to random weights."""
    b, h = BACKBONE.path(), HEADS.path()
    if b is None or h is None:
        return None, unavailable("LPIPS", BACKBONE, HEADS)
    return load_lpips(b, h, os.environ.get(NET_ENV, net)), None
