"""Rendering a trained model to files: the library behind `coin-cl render` (test/train views and an
orbit, each image with a colour-mapped depth map)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from coin_cl.scene.conventions import look_at


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


def _viewmat(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(look_at(eye.numpy(), target.numpy(), up.numpy()), dtype=torch.float32)


def orbit_cameras(cams, n: int, model, step: int, backend: str):
    """`n` cameras on a circle in the mean camera's image plane, looking at the scene's median
    depth along the mean view direction (suits forward-facing captures). `cams`: `Camera`s."""
    from coin_cl.scene.types import Camera

    centers = torch.stack([c.center_t for c in cams])
    c0 = centers.mean(0)
    fwd = torch.stack([c.viewmat_t[2, :3] for c in cams]).mean(0)
    fwd = fwd / fwd.norm()
    up = -torch.stack([c.viewmat_t[1, :3] for c in cams]).mean(0)
    base = cams[0]
    V = _viewmat(c0, c0 + fwd, up)
    right, down = V[0, :3], V[1, :3]
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
        Vi = _viewmat(eye, target, up)
        result.append(Camera(base.K, Vi, base.width, base.height, f"orbit{i:03d}"))
    return result


def _run_folder(run: Path) -> tuple[Path, dict]:
    """(checkpoint of the final stage, {"train": [...], "test": [...]} camera JSON) of a `coin-cl run`
    folder: the stage its eval rendered (4_ted, or 2_refgs when TE-D was skipped)."""
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.scene import load_scene

    man = run / "eval" / "manifest.json"
    final = json.loads(man.read_text())["settings"]["final"] if man.is_file() else None
    for name in ([final] if final else []) + ["4_ted", "2_refgs"]:
        cands = (
            sorted((run / name).rglob(CKPT_NAME), key=lambda p: p.stat().st_mtime)
            if (run / name).is_dir()
            else []
        )
        if cands:
            break
    else:
        raise FileNotFoundError(
            f"{run} is a coin-cl run folder without a trained stage yet (4_ted or 2_refgs)"
        )
    scene = load_scene(run / "0_scene" / "scene")
    cams = {k: [scene.cameras[i].to_json() for i in idx] for k, idx in (("train", scene.train_idx),
                                                                      ("test", scene.test_idx))}  # fmt: skip
    return cands[-1], cams


def render_checkpoint(
    out_dir: Path, views: str = "test", frames: int = 48, backend: str = "opencl", device=None
) -> tuple[int, Path]:
    """Render the model trained into `out_dir` (its checkpoint and cameras.json, or a `coin-cl run`
    folder: its final stage's model and its scene's cameras): `views` is "test",
    "train" or "orbit" (`frames` cameras from `orbit_cameras`). Writes an image and a depth map per
    view under `out_dir/renders/<views>/` (and `renders/orbit.gif` for the orbit); returns the
    number of views and the path written (the folder, or the GIF)."""
    import imageio.v2 as imageio

    from coin_cl.gs.trainer import CAMERAS_NAME, CKPT_NAME, cameras_from_json, model_from_state
    from coin_cl.scene.io import atomic_write, to_uint8, write_png

    out_dir = Path(out_dir)
    ckpt = out_dir / CKPT_NAME
    if (out_dir / "run.json").is_file() and not ckpt.is_file():
        ckpt, cams = _run_folder(out_dir)
    elif not ckpt.is_file():
        raise FileNotFoundError(
            f"{ckpt} not found: train into {out_dir} first (or give a coin-cl run folder)"
        )
    else:
        cams = json.loads((out_dir / CAMERAS_NAME).read_text())
    state = torch.load(ckpt, weights_only=False)
    model = model_from_state(state["model"])
    model.device = device
    step = int(state["trainer"]["step"])
    if views == "orbit":
        cameras = orbit_cameras(cameras_from_json(cams["train"]), frames, model, step, backend)
    else:
        cameras = cameras_from_json(cams[views])
    dest = out_dir / "renders" / views
    dest.mkdir(parents=True, exist_ok=True)
    strips = []
    for i, cam in enumerate(cameras):
        with torch.no_grad():
            r = model.render(cam, step, backend=backend, return_depth=True)
        img = to_uint8(r.image.clamp(0, 1).numpy())
        dep = colorize_depth(r.depth.numpy(), r.alpha.numpy())
        stem = f"{i:03d}_{Path(cam.name).stem}" if cam.name else f"{i:03d}"
        write_png(dest / f"{stem}.png", img)
        write_png(dest / f"{stem}_depth.png", dep)
        strips.append(np.concatenate([img, dep], 1))
    if views == "orbit":
        gif = out_dir / "renders" / "orbit.gif"
        atomic_write(gif, lambda p: imageio.mimsave(p, strips, format="GIF", duration=1000 / 24, loop=0))
        return len(strips), gif
    return len(strips), dest
