"""The splatting engine: OpenCL kernels as differentiable torch ops, their float64 twins, the runtime.

rendering   the public API: rasterize = project -> bin_tiles -> rasterize_to_pixels
ops/        one module per kernel file of kernels/ (thin autograd wrappers)
reference   pure-torch float64 twins with the same signatures (tests, error columns)
devices     device listing, probing and choice; where the kernel sources are
runtime     context/queue, program cache, shared buffers
icd         registration of pip-installed OpenCL implementations
constants   every constant, mirrored in kernels/common.h
geometry    small math the fast path and the twins share
"""

from coin_cl.engine.errors import NoDeviceError, PairOverflowError
from coin_cl.engine.gaussians import Gaussians
from coin_cl.engine.ops.warp import support_mask, warp_features
from coin_cl.engine.rendering import (
    bin_tiles,
    decode_neural_gaussians,
    project,
    rasterize,
    rasterize_to_pixels,
    ssim_map,
)
from coin_cl.engine.runtime import DeviceLike, Runtime, get_runtime, resolve_device

__all__ = [
    "DeviceLike",
    "Gaussians",
    "NoDeviceError",
    "PairOverflowError",
    "Runtime",
    "bin_tiles",
    "decode_neural_gaussians",
    "get_runtime",
    "project",
    "rasterize",
    "rasterize_to_pixels",
    "resolve_device",
    "ssim_map",
    "support_mask",
    "warp_features",
]
