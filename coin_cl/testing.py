"""Seeded scenes for tests and benchmarks: random Gaussians and simple pinhole cameras."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from coin_cl.engine.gaussians import Gaussians

__all__ = [
    "Gaussians", "garden_like", "hostile_checkpoint", "look_at_camera", "plant_marker", "random_gaussians"
]  # fmt: skip


def look_at_camera(
    width: int,
    height: int,
    fov_deg: float = 60.0,
    eye=(0.0, 0.0, 0.0),
    cx=None,
    cy=None,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor]:
    """viewmat [4,4] (camera at `eye`, looking down +z) and K [3,3] for a width x height image."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor(
        [[f, 0, width / 2 if cx is None else cx], [0, f, height / 2 if cy is None else cy], [0, 0, 1]],
        dtype=dtype,
    )
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, 3] = -torch.tensor(eye, dtype=dtype)
    return viewmat, K


def camera_looking_at(eye, target, width: int, height: int, f: float, name: str = "v.png"):
    """A `coin_cl.scene.Camera` of `width` x `height` px and focal `f` px at `eye` looking at
    `target`, world z up (`conventions.look_at`), the principal point at the image's centre."""
    import numpy as np

    from coin_cl.scene.conventions import look_at
    from coin_cl.scene.types import Camera

    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)
    return Camera(K=K, viewmat=look_at(eye, target, (0.0, 0.0, 1.0)), width=width, height=height, name=name)


def random_gaussians(
    n: int,
    seed: int = 0,
    channels: int = 3,
    depth: float = 4.0,
    spread: float = 1.0,
    scale_range: tuple[float, float] = (0.02, 0.15),
    dtype: torch.dtype = torch.float64,
) -> Gaussians:
    """N Gaussians in front of a camera at the origin looking down +z (fresh seeded randoms)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread
    means[:, 2] = depth + means[:, 2].abs() * 0.5
    lo, hi = scale_range
    return Gaussians(
        means=means,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=dtype),
        opacities=torch.rand(n, generator=g, dtype=dtype),
        colors=torch.rand(n, channels, generator=g, dtype=dtype),
    )


def garden_like(points: Tensor, n: int, seed: int = 0, jitter: float = 0.5, channels: int = 3) -> Gaussians:
    """gsplat-test-style Gaussians on a real point cloud: points replicated with jitter, scales
    U[1e-4, 0.02], random rotations, opacities U[0, 1] (float32)."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, points.shape[0], (n,), generator=g)
    means = points[idx].to(torch.float32) + torch.randn(n, 3, generator=g) * jitter
    return Gaussians(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * (0.02 - 1e-4) + 1e-4,
        opacities=torch.rand(n, generator=g),
        colors=torch.rand(n, channels, generator=g),
    )


def plant_marker(marker: str) -> dict:
    """Write the file `marker`: the payload of `hostile_checkpoint`, so a test sees whether it ran."""
    from pathlib import Path

    Path(marker).write_text("the checkpoint's code ran")
    return {}


class _Payload:
    """Unpickles by calling `plant_marker(marker)`: code run by merely loading the file."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (plant_marker, (self.marker,))


def hostile_checkpoint(path, marker) -> None:
    """Write at `path` a torch.save file shaped like a trainer checkpoint whose unpickling writes
    the file `marker` (`plant_marker`): loaded with weights_only=False, the marker appears."""
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    state = {"model": _Payload(str(marker)), "trainer": {"step": 1}, "state_dict": {}, "info": {}}
    torch.save(state, path)
