"""Public rendering API: `rasterize` = `project` + `rasterize_to_pixels`, all differentiable.

Conventions: `viewmat` is world-to-camera [4, 4] in OpenCV axes (x right, y down, z forward);
`K` is [3, 3] pinhole in pixels with pixel (x, y) centred at (x + 0.5, y + 0.5); quaternions are
(w, x, y, z) and need not be normalised; scales and opacities are activated (not log / logit).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.errors import NonFiniteInputError
from coin_cl.engine.geometry import finite_rows

log = logging.getLogger(__name__)

Device = Any  # a `Runtime`, a device-name substring, or None for the default device


def _backend(name: str):
    # Imported on use: the fast path never loads the twins, the twins never load OpenCL.
    if name == "opencl":
        from coin_cl.engine import ops

        return ops
    if name == "torch":
        from coin_cl.engine import reference

        return reference
    raise ValueError(f"unknown backend {name!r}: use 'opencl' or 'torch'")


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = cst.NEAR_PLANE,
    far: float = cst.FAR_PLANE,
    backend: str = "opencl",
    device: Device = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project Gaussians to screen space; see `coin_cl.engine.reference.project` for the outputs.

    device: the OpenCL device (a `Runtime` or a name substring; default `get_runtime()`).
    """
    return _backend(backend).project(
        means, quats, scales, viewmat, K, width, height, near, far, device=device
    )


def bin_tiles(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    backend: str = "opencl",
    device: Device = None,
):
    """Bin projected splats to 16x16 tiles, front to back; see `coin_cl.engine.ops.bin_tiles`.

    The result can be passed as `bins=` to `rasterize_to_pixels` by every pass over one view.
    """
    return _backend(backend).bin_tiles(
        means2d, conics, opacities, depths, radii, width, height, max_pairs, device=device
    )


def rasterize_to_pixels(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    stats: dict | None = None,
    bins: Any = None,
    backend: str = "opencl",
    device: Device = None,
) -> tuple[Tensor, Tensor]:
    """Composite projected splats; see `coin_cl.engine.reference.rasterize_to_pixels`.

    bins: a `bin_tiles` result for these splats (binned here when None).
    """
    return _backend(backend).rasterize_to_pixels(
        means2d, conics, opacities, features, depths, radii, width, height, background,
        max_pairs=max_pairs, stats=stats, device=device, bins=bins,
    )  # fmt: skip


def decode_neural_gaussians(
    anchors: Tensor,
    offsets: Tensor,
    scaling: Tensor,
    opacity: Tensor,
    cov: Tensor,
    color: Tensor,
    vidx: Tensor,
    sidx: Tensor,
    backend: str = "opencl",
    device: Device = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Scaffold-GS' neural Gaussians from its MLP outputs, differentiably; shapes in
    `coin_cl.engine.reference.decode_neural_gaussians`. The OpenCL op builds no per-offset
    temporaries (one work-item per drawn Gaussian forward, per visible anchor backward)."""
    return _backend(backend).decode_neural_gaussians(
        anchors, offsets, scaling, opacity, cov, color, vidx, sidx, device=device
    )


def _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background):
    n = means.shape[0]
    shapes = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
        "viewmat": (viewmat, (4, 4)),
        "K": (K, (3, 3)),
    }
    for name, (t, shape) in shapes.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {shape}")
    if colors.dim() != 2 or colors.shape[0] != n or not 1 <= colors.shape[1] <= cst.MAX_CHANNELS - 1:
        raise ValueError(
            f"colors has shape {tuple(colors.shape)}, expected [{n}, C] with 1 <= C < {cst.MAX_CHANNELS}"
        )
    if background is not None and tuple(background.shape) != (colors.shape[1],):
        raise ValueError(f"background has shape {tuple(background.shape)}, expected ({colors.shape[1]},)")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size {width}x{height} must be at least 1x1")
    for name, t in (("viewmat", viewmat), ("K", K)):
        if not torch.isfinite(t).all():
            raise NonFiniteInputError(f"{name} has non-finite entries: the camera must be finite")
    if background is not None and not torch.isfinite(background.detach()).all():
        raise NonFiniteInputError(
            f"background is {background.detach().cpu().tolist()}: it must be finite (NaN or Inf would "
            "fill every pixel the splats leave uncovered); pass a colour such as zeros or ones"
        )
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    background: Tensor | None = None,
    near: float = cst.NEAR_PLANE,
    far: float = cst.FAR_PLANE,
    return_depth: bool = False,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    backend: str = "opencl",
    device: Device = None,
) -> tuple[Tensor, Tensor, Tensor | None, dict[str, Any]]:
    """Render N 3D Gaussians into one camera, differentiably.

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N] in [0, 1],
        colors [N, C] (any C from 1 to 127: RGB, features, ...), viewmat [4, 4], K [3, 3].
        background: [C] colour behind the splats (default zeros).
        near, far: camera-z clip planes. return_depth: also render accumulated depth.
        max_pairs: cap on (tile, Gaussian) pairs; exceeding it raises `PairOverflowError`
            (OpenCL backend) rather than failing an allocation.
        backend: 'opencl' (the kernels) or 'torch' (the float64-capable twin, slow).
        device: the OpenCL device: a `Runtime`, a name substring ("intel", "pthread", "nvidia"),
            or None for the default (`COIN_CL_DEVICE`, else the first working device).
    Returns:
        image [H, W, C]; alpha [H, W] (1 - final transmittance); depth [H, W] or None, the
        alpha-weighted camera z sum_i w_i z_i (divide by alpha for the expected depth); meta with
        'means2d' [N, 2] (in the graph: call .retain_grad() for densification), 'radii' [N],
        'visible' [N] bool, 'n_nonfinite' (Gaussians culled for NaN/Inf input), 'n_pairs'.
    Gradients flow to means, quats, scales, opacities, colors (and background).
    """
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background)
    be = _backend(backend)
    means2d, conics, depths, radii = be.project(
        means, quats, scales, viewmat, K, int(width), int(height), near, far, device=device
    )
    # Projection culls NaN/Inf geometry; NaN/Inf in opacity or colour would poison every pixel the
    # splat covers, so those Gaussians are culled here and counted.
    finite_all = finite_rows(means, quats, scales, opacities, colors)
    radii = radii.masked_fill(~finite_all, 0)
    n_nonfinite = int((~finite_all).sum())
    if n_nonfinite:
        log.warning("culled %d Gaussians with NaN/Inf inputs (meta['n_nonfinite'])", n_nonfinite)

    feats = torch.cat([colors, depths[:, None].to(colors.dtype)], 1) if return_depth else colors
    bg = background
    if return_depth and background is not None:
        bg = torch.cat([background, background.new_zeros(1)])
    stats: dict[str, Any] = {}
    image, alpha = be.rasterize_to_pixels(
        means2d, conics, opacities, feats, depths, radii, int(width), int(height), bg,
        max_pairs=max_pairs, stats=stats, device=device,
    )  # fmt: skip
    depth = None
    if return_depth:
        image, depth = image[..., :-1], image[..., -1]
    meta = {
        "means2d": means2d,
        "conics": conics,
        "depths": depths,
        "radii": radii,
        "visible": radii > 0,
        "n_nonfinite": n_nonfinite,
        "tiles": (math.ceil(width / cst.TILE_SIZE), math.ceil(height / cst.TILE_SIZE)),
        **stats,
    }
    return image, alpha, depth, meta


def ssim_map(
    a: Tensor,
    b: Tensor,
    window: int = 11,
    sigma: float = 1.5,
    c1: float = 0.01**2,
    c2: float = 0.03**2,
    backend: str = "opencl",
    device: Device = None,
) -> Tensor:
    """[B, H, W] per-pixel SSIM of a, b [B, H, W, C] (Gaussian window, zero padding), averaged over
    channels; see `coin_cl.engine.reference.ssim_map`. The OpenCL op differentiates `a` only."""
    return _backend(backend).ssim_map(a, b, window, sigma, c1, c2, device=device)
