"""One set of renderer inputs: the container every producer of Gaussians hands to the engine."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Gaussians:
    """means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] and opacities [N] (activated),
    colors [N, C] (RGB or any features)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor

    def tensors(self) -> list[Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.colors]

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def to(self, dtype: torch.dtype) -> Gaussians:
        return Gaussians(*(t.to(dtype) for t in self.tensors()))

    def requires_grad_(self) -> Gaussians:
        for t in self.tensors():
            t.requires_grad_(True)
        return self
