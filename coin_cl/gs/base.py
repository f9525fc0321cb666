"""What every trainable model gives the trainer (vanilla 3DGS and Scaffold-GS both implement it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from coin_cl.gs.data import Camera
from coin_cl.gs.optim import ParamOptimizer

if TYPE_CHECKING:
    from coin_cl.gs.splats import Splats

# gsplat / 3DGS measure the screen-space gradient in NDC-like units: the gradient with respect to
# the pixel position times half the image size (dL/dx_ndc = dL/dx_px * W / 2). All `grad2d`
# thresholds in this package are in those units, so the familiar 0.0002 keeps its meaning.


@dataclass
class RenderOutput:
    """One rendered view: image [H, W, 3], alpha [H, W], depth [H, W] (expected z, or None),
    `meta` from the rasterizer (means2d [M, 2], radii [M], ...) plus what strategies and loss
    terms read: width, height, scales [M, 3] (the drawn Gaussians' activated scales) and
    model-specific entries (Scaffold-GS: anchor_visible, selected, neural_opacity)."""

    image: Tensor
    alpha: Tensor
    depth: Tensor | None
    meta: dict[str, Any] = field(default_factory=dict)


def ndc_grad_norm(means2d: Tensor, width: int, height: int) -> Tensor:
    """[M] norm of the screen-space gradient in NDC units (needs means2d.grad)."""
    g = means2d.grad
    if g is None:
        return means2d.new_zeros(means2d.shape[0])
    scale = g.new_tensor([0.5 * width, 0.5 * height])
    return (g * scale).norm(dim=-1)


def splat(
    cam: Camera,
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    *,
    backend: str,
    background: Tensor | None,
    return_depth: bool,
    training: bool,
    device: Any = None,
) -> tuple[Tensor, Tensor, Tensor | None, dict[str, Any]]:
    """Rasterize activated Gaussians into `cam` (see `coin_cl.rasterize`); keeps the screen-space
    gradient for densification when training and turns accumulated depth into expected depth."""
    from coin_cl.engine.rendering import rasterize

    image, alpha, depth, meta = rasterize(
        means, quats, scales, opacities, colors, cam.viewmat_t, cam.K_t, cam.width, cam.height,
        background=background, return_depth=return_depth, backend=backend, device=device,
    )  # fmt: skip
    if training and meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    if depth is not None:
        depth = depth / alpha.clamp_min(1e-6)
    return image, alpha, depth, meta


class Model:
    """Interface: see `GaussianModel` and `ScaffoldModel`. A model holds parameters (all in
    `optimizer`, a `ParamOptimizer`), renders, exports and saves; densification is a
    `coin_cl.gs.strategy.Strategy` and the loss a list of `coin_cl.gs.terms.LossTerm`s."""

    kind: str = ""
    optimizer: ParamOptimizer
    # The OpenCL device renders go to (a Runtime or a name; None: the default device).
    device: Any = None
    # The fused training path (index gathers, fused kernels); False selects the earlier unfused
    # path, kept so that `benchmarks/train.py --throughput` compares both in one run.
    fused: bool = True

    def render(
        self,
        cam: Camera,
        step: int,
        *,
        backend: str = "opencl",
        background: Tensor | None = None,
        return_depth: bool = False,
        training: bool = False,
    ) -> RenderOutput:
        raise NotImplementedError

    @property
    def n_primitives(self) -> int:
        raise NotImplementedError

    def learning_rates(self) -> dict[str, Any]:
        """{parameter name: constant rate or `ExpSchedule`} as the model's config gives them (what
        its optimizer is built with; rebuilt from a changed config by `continue_rates`, so that a
        model rebuilt from a checkpoint computes the very same rates)."""
        raise NotImplementedError

    def export_gaussians(self, cam_center: Tensor | None = None) -> Splats:
        """Plain 3DGS Gaussians (`coin_cl.gs.splats.Splats`, detached). Models whose colour is
        decoded per view freeze it as seen from `cam_center` [3] (default: the origin)."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        raise NotImplementedError


def inverse_sigmoid(x: Tensor | float) -> Tensor:
    x = torch.as_tensor(x, dtype=torch.float32)
    return torch.log(x / (1 - x))
