"""torch.autograd Functions that launch the OpenCL kernels, one module per kernel file:

    project.py    <- kernels/project.cl
    bin.py        <- kernels/bin.cl
    rasterize.py  <- kernels/rasterize_cpu.cl, kernels/rasterize_gpu.cl (two variants of one pass)
    reduce.py     <- kernels/reduce.cl
    warp.py       <- kernels/warp.cl (feature warping through a point cloud)
    decode.py     <- kernels/decode.cl (Scaffold-GS neural Gaussians after the MLPs)
    ssim.py       <- kernels/ssim.cl (per-pixel SSIM of the photometric loss)

Each public function has the signature of its float64 twin in `coin_cl.engine.reference`.
Everything crosses into the kernels as contiguous float32 / int32 tensors wrapped by the runtime
(aliased on unified-memory devices, copied and counted elsewhere).
"""

from coin_cl.engine.ops.bin import TileBins, bin_tiles
from coin_cl.engine.ops.decode import decode_neural_gaussians
from coin_cl.engine.ops.project import project
from coin_cl.engine.ops.rasterize import deterministic, kernel_variant, raster_variant, rasterize_to_pixels
from coin_cl.engine.ops.ssim import ssim_map

__all__ = [
    "TileBins",
    "bin_tiles",
    "decode_neural_gaussians",
    "deterministic",
    "kernel_variant",
    "project",
    "raster_variant",
    "rasterize_to_pixels",
    "ssim_map",
]
