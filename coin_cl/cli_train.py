"""`coin-cl train` and `coin-cl render`: Gaussian-splatting reconstruction of a scene folder."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)


def add_commands(subparsers) -> None:
    t = subparsers.add_parser("train", help="train vanilla 3DGS or Scaffold-GS on a scene folder")
    t.add_argument("scene_dir", type=Path)
    t.add_argument("--model", choices=("scaffold", "3dgs"), default="scaffold")
    t.add_argument("--iters", type=int, default=30_000)
    t.add_argument("--resolution", type=float, default=0.5, help="image scale (0.5 = half size)")
    t.add_argument("--out", type=Path, required=True, help="output folder (resumes if it has ckpt.pt)")
    t.add_argument(
        "--holdout",
        type=int,
        default=8,
        help="hold out every Nth training view for evaluation (0: use the scene's test views)",
    )
    t.add_argument(
        "--targets",
        choices=("images", "inpainted"),
        default="images",
        help="train on the images, or on the per-view 2D inpaints (RGB_inpainted)",
    )
    t.add_argument("--exclude-masks", action="store_true", help="leave object masks out of the loss")
    t.add_argument("--max-minutes", type=float, default=0.0, help="stop after this much training time")
    t.add_argument("--eval-every", type=int, default=0)
    t.add_argument("--ckpt-every", type=int, default=1000)
    t.add_argument("--backend", choices=("opencl", "torch"), default="opencl")
    t.add_argument("--device", default=None, help="OpenCL device name substring (default: coin-cl doctor's)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint in --out")
    t.set_defaults(func=cmd_train)

    r = subparsers.add_parser("render", help="render a trained model: images, depth maps, an orbit")
    r.add_argument("out_dir", type=Path)
    r.add_argument("--views", choices=("test", "train", "orbit"), default="test")
    r.add_argument("--frames", type=int, default=48, help="orbit frames")
    r.add_argument("--backend", choices=("opencl", "torch"), default="opencl")
    r.add_argument("--device", default=None, help="OpenCL device name substring (default: coin-cl doctor's)")
    r.set_defaults(func=cmd_render)


def cmd_train(args: argparse.Namespace) -> int:
    from coin_cl import load_scene
    from coin_cl.gs.trainer import TrainConfig, make_trainer, scaled_model_config
    from coin_cl.scene.splits import inpainted_targets, split_indices

    scene = load_scene(args.scene_dir, resolution=args.resolution)
    tr_idx, te_idx = split_indices(scene, args.holdout)
    images = inpainted_targets(scene) if args.targets == "inpainted" else None
    cfg = TrainConfig(
        model=args.model,
        iters=args.iters,
        backend=args.backend,
        seed=args.seed,
        eval_every=args.eval_every,
        ckpt_every=args.ckpt_every,
        max_seconds=60.0 * args.max_minutes,
    )
    tr = make_trainer(
        scene, tr_idx, te_idx, cfg, args.out, images,
        scaled_model_config(args.model, args.iters), args.exclude_masks, resume=not args.fresh,
        device=args.device,
    )  # fmt: skip
    res = tr.train()
    print(
        f"{args.model}: {res['step']} steps in {res['train_seconds']:.0f} s, "
        f"{res['n']} primitives, held-out PSNR {res.get('psnr', math.nan):.2f} dB "
        f"SSIM {res.get('ssim', math.nan):.4f}; wrote {args.out}"
    )
    return 0


def colorize_depth(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """[H, W] depth -> [H, W, 3] uint8 turbo colour map of inverse depth (near = warm);
    pixels with alpha < 0.5 are black."""
    import cv2

    valid = (alpha > 0.5) & np.isfinite(depth) & (depth > 0)
    inv = np.zeros_like(depth)
    inv[valid] = 1.0 / depth[valid]
    if valid.any():
        lo, hi = np.percentile(inv[valid], [1, 99])
        inv = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = cv2.applyColorMap((inv * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    rgb[~valid] = 0
    return np.ascontiguousarray(rgb)


def orbit_cameras(cams, n: int, model, step: int, backend: str):
    """`n` cameras on a circle in the mean camera's image plane, looking at the scene's median
    depth along the mean view direction (suits forward-facing captures)."""
    from coin_cl.gs.data import Camera

    centers = torch.stack([c.center for c in cams])
    c0 = centers.mean(0)
    fwd = torch.stack([c.viewmat[2, :3] for c in cams]).mean(0)
    fwd = fwd / fwd.norm()
    up = -torch.stack([c.viewmat[1, :3] for c in cams]).mean(0)
    right = torch.linalg.cross(fwd, up)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    base = cams[0]
    V = torch.eye(4)
    V[:3, :3], V[:3, 3] = R, -R @ c0
    mid = Camera(base.K, V, base.width, base.height, "mean")
    with torch.no_grad():
        out = model.render(mid, step, backend=backend, return_depth=True)
    d = out.depth[out.alpha > 0.5]
    focus_depth = float(d.median()) if d.numel() else 1.0
    target = c0 + fwd * focus_depth
    rel = centers - c0
    radius = 0.5 * float(torch.stack([rel @ right, rel @ down], 1).abs().max())
    radius = radius if radius > 0 else 0.05 * focus_depth
    result = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = c0 + radius * (math.cos(a) * right + math.sin(a) * down)
        f = target - eye
        f = f / f.norm()
        r = torch.linalg.cross(f, up)
        r = r / r.norm()
        dn = torch.linalg.cross(f, r)
        Ri = torch.stack([r, dn, f])
        Vi = torch.eye(4)
        Vi[:3, :3], Vi[:3, 3] = Ri, -Ri @ eye
        result.append(Camera(base.K, Vi, base.width, base.height, f"orbit{i:03d}"))
    return result


def cmd_render(args: argparse.Namespace) -> int:
    import imageio.v2 as imageio

    from coin_cl.gs.trainer import CAMERAS_NAME, CKPT_NAME, cameras_from_json, model_from_state
    from coin_cl.scene.io import atomic_write, to_uint8, write_png

    out_dir = args.out_dir
    ckpt = out_dir / CKPT_NAME
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt} not found: train into {out_dir} first")
    state = torch.load(ckpt, weights_only=False)
    model = model_from_state(state["model"])
    model.device = args.device
    step = int(state["trainer"]["step"])
    import json

    cams = json.loads((out_dir / CAMERAS_NAME).read_text())
    if args.views == "orbit":
        views = orbit_cameras(cameras_from_json(cams["train"]), args.frames, model, step, args.backend)
    else:
        views = cameras_from_json(cams[args.views])
    dest = out_dir / "renders" / args.views
    dest.mkdir(parents=True, exist_ok=True)
    frames = []
    for i, cam in enumerate(views):
        with torch.no_grad():
            r = model.render(cam, step, backend=args.backend, return_depth=True)
        img = to_uint8(r.image.clamp(0, 1).numpy())
        dep = colorize_depth(r.depth.numpy(), r.alpha.numpy())
        stem = f"{i:03d}_{Path(cam.name).stem}" if cam.name else f"{i:03d}"
        write_png(dest / f"{stem}.png", img)
        write_png(dest / f"{stem}_depth.png", dep)
        frames.append(np.concatenate([img, dep], 1))
    if args.views == "orbit":
        atomic_write(
            out_dir / "renders" / "orbit.gif",
            lambda p: imageio.mimsave(p, frames, format="GIF", duration=1000 / 24, loop=0),
        )
        print(f"wrote {len(frames)} frames and {out_dir / 'renders' / 'orbit.gif'}")
    else:
        print(f"wrote {len(frames)} images and depth maps to {dest}")
    return 0
