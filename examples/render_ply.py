"""Render a 3DGS PLY (the standard layout: 3DGS, gsplat, coin-cl exports) with the OpenCL engine.

    python examples/render_ply.py point_cloud.ply --out renders/ [--size 640 480] [--frames 24]

Cameras orbit the Gaussians' centre, looking at it (OpenCV axes: x right, y down, z forward).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

import coin_cl
from coin_cl.gs.splats import Splats
from coin_cl.scene.io import to_uint8, write_png


def orbit_viewmat(center: np.ndarray, radius: float, angle: float, height: float) -> torch.Tensor:
    """World-to-camera [4, 4] of a camera on a circle around `center`, looking at it."""
    eye = center + np.array([radius * math.sin(angle), -height, -radius * math.cos(angle)])
    fwd = (center - eye) / np.linalg.norm(center - eye)
    right = np.cross([0.0, 1.0, 0.0], fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = R, -R @ eye
    return torch.tensor(vm, dtype=torch.float32)


def main(argv: list[str] | None = None) -> list[Path]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", type=Path)
    ap.add_argument("--out", type=Path, default=Path("renders"))
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--device", default=None, help="OpenCL device name substring")
    args = ap.parse_args(argv)

    g = Splats.from_ply(args.ply)
    center = g.means.mean(0).numpy()
    radius = 2.5 * float(np.linalg.norm(g.means.numpy() - center, axis=1).mean())
    W, H = args.size
    f = 0.8 * W
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    args.out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(args.frames):
        vm = orbit_viewmat(center, radius, 2 * math.pi * i / args.frames, 0.3 * radius)
        eye = -vm[:3, :3].T @ vm[:3, 3]
        gs = g.gaussians(cam_center=eye)  # the renderer's inputs, SH colour seen from this camera
        img, _, _, meta = coin_cl.rasterize(*gs.tensors(), vm, K, W, H, device=args.device)
        paths.append(args.out / f"frame_{i:03d}.png")
        write_png(paths[-1], to_uint8(img.clamp(0, 1).numpy()))
    print(f"rendered {len(paths)} frames of {len(g)} Gaussians to {args.out}/")
    return paths


if __name__ == "__main__":
    main()
