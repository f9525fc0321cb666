"""Plain-torch networks (no torchvision, no downloads): LPIPS backbones + heads and pytorch-fid's
Inception-v3 now; the UNet, the discriminator and DINO later. Every network loads its weights by one
rule (`coin_cl.nets.weights`): an environment variable names a local file; unset, the network is
unavailable with a reason that names the variable and the expected file."""

from .inception import FIDInception, inception_from_env, load_inception
from .lpips import LPIPS, load_lpips, lpips_from_env
from .weights import WeightFile, load_state_dict, unavailable

__all__ = [
    "LPIPS",
    "FIDInception",
    "WeightFile",
    "inception_from_env",
    "load_inception",
    "load_lpips",
    "load_state_dict",
    "lpips_from_env",
    "unavailable",
]
