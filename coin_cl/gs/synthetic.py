"""A tiny hand-placed Gaussian scene with exact ground-truth renders, for tests and smoke runs.

The ground truth is rendered by the same rasterizer the models train through, so a model that
reaches a high PSNR here proves that gradients flow end to end (not that the renderer is right;
the renderer has its own tests against its float64 twin).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.data import Camera, View
from coin_cl.scene.conventions import look_at


@dataclass
class TinyScene:
    """Ground-truth Gaussians (means [N,3] ...) and their renders from a ring of cameras."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    views: list[View]

    def noisy_points(self, sigma: float = 0.05, seed: int = 1) -> np.ndarray:
        """[N, 3] the true means plus Gaussian noise: a stand-in for SfM points."""
        g = torch.Generator().manual_seed(seed)
        return (self.means + sigma * torch.randn(self.means.shape, generator=g)).numpy()


def tiny_scene(
    n: int = 40,
    width: int = 32,
    height: int = 24,
    n_views: int = 8,
    seed: int = 0,
    backend: str = "torch",
) -> TinyScene:
    """`n` random Gaussians in a 1.6-wide cube, seen from `n_views` cameras on a ring of
    radius 3.5 around it (black background)."""
    from coin_cl.engine.rendering import rasterize

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.08
    opac = torch.rand(n, generator=g) * 0.5 + 0.5
    cols = torch.rand(n, 3, generator=g)
    K = torch.tensor([[30.0 * width / 32, 0, width / 2], [0, 30.0 * width / 32, height / 2], [0, 0, 1]])
    views = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        eye = [3.5 * math.sin(a), 0.6 * math.cos(3 * a), -3.5 * math.cos(a)]
        vm = torch.tensor(look_at(eye, (0.0, 0.0, 0.0), (0.0, -1.0, 0.0)), dtype=torch.float32)
        cam = Camera(K, vm, width, height, f"view{i}")
        with torch.no_grad():
            img, _, _, _ = rasterize(means, quats, scales, opac, cols, cam.viewmat_t, cam.K_t,
                                     width, height, background=torch.zeros(3), backend=backend)  # fmt: skip
        views.append(View(cam, img.float().clamp(0, 1)))
    return TinyScene(means, quats, scales, opac, cols, views)
