"""coin-cl: CoIn 3D scene inpainting on a portable OpenCL Gaussian-splatting engine.

Public engine API (differentiable torch ops, OpenCL underneath; `coin_cl.engine`):
    rasterize, project, bin_tiles, rasterize_to_pixels, Gaussians, get_runtime
Scenes and evaluation:
    load_scene, metrics
CoIn (the whole method; coin_cl.pipeline):
    inpaint, CoInConfig
"""

import os

# torch and PoCL share the cores; torch's OpenMP threads spin-wait by default and then starve
# the OpenCL worker threads (10-100x slowdowns measured). Must be set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

_LAZY = {
    "rasterize": "coin_cl.engine",
    "project": "coin_cl.engine",
    "bin_tiles": "coin_cl.engine",
    "rasterize_to_pixels": "coin_cl.engine",
    "get_runtime": "coin_cl.engine",
    "Gaussians": "coin_cl.engine",
    "PairOverflowError": "coin_cl.engine",
    "NoDeviceError": "coin_cl.engine",
    "warp_features": "coin_cl.engine",
    "load_scene": "coin_cl.scene",
    "inpaint": "coin_cl.pipeline.coin",
    "CoInConfig": "coin_cl.pipeline.coin",
}


def __getattr__(name: str):
    # Lazy so that `import coin_cl` stays cheap and OpenCL is only touched when used.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'coin_cl' has no attribute {name!r}")
