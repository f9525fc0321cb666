"""A procedural Gaussian scene for the demo's turntable (no data needed): a textured torus knot
over a checkered floor disc, and the camera circling it."""

from __future__ import annotations

import math

import torch

from coin_cl.engine import Gaussians

from .conventions import look_at


def embedded_scene(n: int = 60_000, seed: int = 0) -> Gaussians:
    """A procedural scene: a textured torus knot of Gaussians over a checkered floor disc (float32,
    centred on the origin, y down)."""
    g = torch.Generator().manual_seed(seed)
    k = n * 2 // 3
    t = torch.rand(k, generator=g) * 2 * math.pi
    p, q = 2, 3
    r = torch.cos(q * t) + 2
    knot = torch.stack([r * torch.cos(p * t), -torch.sin(q * t), r * torch.sin(p * t)], 1) * 0.35
    knot = knot + torch.randn(k, 3, generator=g) * 0.06
    hue = (t / (2 * math.pi))[:, None]
    knot_col = 0.5 + 0.5 * torch.cos(2 * math.pi * (hue + torch.tensor([0.0, 0.33, 0.67])))
    m = n - k
    rad = 1.6 * torch.sqrt(torch.rand(m, generator=g))
    ang = torch.rand(m, generator=g) * 2 * math.pi
    floor = torch.stack([rad * torch.cos(ang), torch.full((m,), 0.75), rad * torch.sin(ang)], 1)
    check = ((floor[:, 0] * 3).floor() + (floor[:, 2] * 3).floor()) % 2
    floor_col = (0.25 + 0.5 * check)[:, None].expand(m, 3) * torch.tensor([1.0, 0.95, 0.85])
    means = torch.cat([knot, floor])
    scales = torch.cat([torch.full((k, 3), 0.025), torch.tensor([0.04, 0.004, 0.04]).expand(m, 3)])
    scales = scales * (0.6 + 0.8 * torch.rand(n, 3, generator=g))
    return Gaussians(
        means=means,
        quats=torch.cat([torch.randn(k, 4, generator=g), torch.tensor([[1.0, 0, 0, 0]]).expand(m, 4)]),
        scales=scales,
        opacities=0.5 + 0.5 * torch.rand(n, generator=g),
        colors=torch.cat([knot_col, floor_col]).clamp(0, 1),
    )


def turntable_viewmat(angle: float, radius: float = 4.0, height: float = -1.2) -> torch.Tensor:
    """[4, 4] float32 world-to-camera of a camera on a circle around the origin (y down), looking
    at it (OpenCV axes)."""
    eye = (radius * math.sin(angle), height, -radius * math.cos(angle))
    return torch.as_tensor(look_at(eye, (0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)), dtype=torch.float32)
