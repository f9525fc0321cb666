"""Rendering to files: the library behind `coin-cl render` (test/train views and an orbit, each
image with a colour-mapped depth map), and the one orbit of the code base (`orbit_cameras`,
`render_views`, `orbit_gif`), which the eval stage (paper 5) and `coin-cl demo` call too."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from coin_cl.scene.conventions import look_at

# One frame of every GIF written here (12.5 frames per second).
GIF_FRAME_MS = 80
# Frames of the eval stage's orbit GIF.
ORBIT_FRAMES = 36
# Every this many pixels of each frame, across and down, feed the GIF's shared palette.
GIF_PALETTE_STRIDE = 4


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


def orbit_cameras(cams: Sequence, n: int, model, step: int, backend: str = "opencl") -> list:
    """`n` cameras [`Camera`] on a circle in the mean camera's image plane (radius: half the
    captured cameras' spread in that plane), looking at the scene's median rendered depth along the
    mean view direction (suits forward-facing captures). `cams`: the captured `Camera`s; `model`
    (rendered once from the mean camera, at `step`) decides the depth looked at."""
    from coin_cl.scene.types import Camera

    if not cams:
        raise ValueError("orbit_cameras needs at least one captured camera")
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


def gif_palette_frames(frames: Sequence[np.ndarray]) -> list:
    """Frames [H, W, 3] uint8 -> PIL images in one 256-colour palette, Floyd-Steinberg dithered.

    The palette is the median cut of every frame at a quarter of its size, taken together: one
    palette for the whole GIF (no colour flicker from frame to frame), and 0.24 s for 36 frames of
    504x284 where a median cut per frame (PIL's default) took 7 s, a step of the budget's eval
    stage; mean absolute error 3.1 levels against 2.3 (measured on SPIn-NeRF renders)."""
    from PIL import Image

    frames = [np.ascontiguousarray(f, dtype=np.uint8) for f in frames]
    if not frames:
        raise ValueError("a GIF needs at least one frame")
    sample = [f[::GIF_PALETTE_STRIDE, ::GIF_PALETTE_STRIDE].reshape(-1, 3) for f in frames]
    mosaic = np.concatenate(sample, 0)[:, None, :]  # [N, 1, 3]: frames of different sizes pool too
    palette = Image.fromarray(mosaic).quantize(256)
    return [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.FLOYDSTEINBERG) for f in frames]


def write_gif(path: Path, frames: Sequence[np.ndarray]) -> None:
    """Frames [H, W, 3] uint8 -> a looping GIF at `GIF_FRAME_MS` per frame in one palette
    (`gif_palette_frames`), written atomically."""
    from coin_cl.scene.io import atomic_write

    images = gif_palette_frames(frames)

    def _save(p: Path) -> None:
        images[0].save(
            p, format="GIF", save_all=True, append_images=images[1:], duration=GIF_FRAME_MS, loop=0
        )

    atomic_write(path, _save)


def render_views(
    render: Callable,
    cameras: Sequence,
    dest: Path | None = None,
    gif: Path | None = None,
    depth: bool = False,
    desc: str = "render",
    names: Sequence[str] | None = None,
) -> list[np.ndarray]:
    """Render each camera and return the frames ([H, W, 3] uint8, or [H, 2W, 3] with the
    colour-mapped depth beside the image when `depth`).

    render: camera -> an object with image [H, W, 3] in [0, 1], alpha [H, W] and (with `depth`)
        depth [H, W] (a `RenderOutput`); called under torch.no_grad().
    dest: a folder for one PNG per view (`<names[i]>.png`; by default `<i:03d>_<name stem>.png`, or
        `<i:03d>.png` for an unnamed camera; `..._depth.png` beside it with `depth`).
    gif: a looping GIF of the frames."""
    from tqdm import tqdm

    from coin_cl.atomic import check_path
    from coin_cl.scene.io import to_uint8, write_png

    if dest is not None:
        check_path(dest).mkdir(parents=True, exist_ok=True)  # made through no link (`confined_to`)
    frames = []
    for i, cam in enumerate(tqdm(cameras, desc=desc, unit="view")):
        with torch.no_grad():
            r = render(cam)
        img = to_uint8(r.image.clamp(0, 1).numpy())
        dep = colorize_depth(r.depth.numpy(), r.alpha.numpy()) if depth else None
        if dest is not None:
            stem = names[i] if names else f"{i:03d}_{Path(cam.name).stem}" if cam.name else f"{i:03d}"
            write_png(Path(dest) / f"{stem}.png", img)
            if dep is not None:
                write_png(Path(dest) / f"{stem}_depth.png", dep)
        frames.append(img if dep is None else np.concatenate([img, dep], 1))
    if gif is not None:
        write_gif(gif, frames)
    return frames


def orbit_gif(
    model,
    cameras: Sequence,
    path: Path,
    frames: int = ORBIT_FRAMES,
    step: int = 10**9,
    backend: str = "opencl",
    dest: Path | None = None,
    depth: bool = False,
) -> list:
    """Render `model` at `step` along `orbit_cameras(cameras, frames)` into the looping GIF `path`
    (and PNGs under `dest`, see `render_views`); returns the orbit's cameras."""
    orbit = orbit_cameras(cameras, frames, model, step, backend)
    render_views(lambda c: model.render(c, step, backend=backend, return_depth=depth), orbit, dest, path,
                 depth, desc="orbit")  # fmt: skip
    return orbit


def _run_folder(run: Path) -> tuple[Path, dict]:
    """(checkpoint of the final stage, {"train": [...], "test": [...]} camera JSON) of a `coin-cl run`
    folder: the stage its eval rendered (4_ted, or 2_refgs when TE-D was skipped)."""
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.pipeline.runner import read_manifest
    from coin_cl.scene import load_scene
    from coin_cl.schema import SchemaError, inside

    man = read_manifest(run / "eval")
    final = None if man is None else man["settings"].get("final")
    if final is not None:
        where = run / "eval" / "manifest.json"
        if not isinstance(final, str):
            raise SchemaError(f"{where}: settings.final is {final!r}, not a stage folder name; delete it")
        inside(run, final, where, "settings.final")  # a stage folder of this run, never outside it
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


def capture_scale(out_dir: Path) -> float:
    """The scale that brings the cameras of a `coin-cl run` folder (or of one of its stages) back to
    its photos' size: 1 / the working resolution its plan.json records."""
    from coin_cl.pipeline.budget import PLAN_FILE, read_plan

    out_dir = Path(out_dir)
    run = next((p for p in (out_dir, *out_dir.parents[:2]) if (p / "run.json").is_file()), None)
    if run is None or not (run / PLAN_FILE).is_file():
        raise ValueError(f"{out_dir} is not a coin-cl run folder (no run.json and plan.json): the "
                         "capture's size is a run's; give --scale a number instead")  # fmt: skip
    res = read_plan(run / PLAN_FILE).key.get("resolution")
    if isinstance(res, bool) or not isinstance(res, int | float) or not (math.isfinite(res) and 0 < res <= 1):
        raise ValueError(f"{run / PLAN_FILE}: key.resolution is {res!r}, not a scale in (0, 1]; delete "
                         "the file and run coin-cl run again, or give --scale a number")  # fmt: skip
    return 1.0 / float(res)


def render_checkpoint(
    out_dir: Path,
    views: str = "test",
    frames: int = 48,
    backend: str = "opencl",
    device=None,
    dest: Path | None = None,
    scale: float | str = 1.0,
) -> tuple[int, Path]:
    """Render the model trained into `out_dir` (its checkpoint and cameras.json, or a `coin-cl run`
    folder: its final stage's model and its scene's cameras): `views` is "test",
    "train" or "orbit" (`frames` cameras from `orbit_cameras`). Writes an image and a depth map per
    view under `dest/<views>/` (and `dest/orbit.gif` for the orbit; `dest` defaults to
    `out_dir/renders`); returns the number of views and the path written (the folder, or the GIF).
    scale: the image size over the cameras' (a run's cameras are at its working resolution);
    "capture": a run's photos' own size (1 / the resolution its plan.json records)."""
    from coin_cl.checkpoint import load_checkpoint, malformed
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CAMERAS_NAME, CKPT_NAME, cameras_from_json

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
        run = next((p for p in out_dir.parents[:2] if (p / "run.json").is_file()), None)
        if views == "test" and not cams.get("test") and run is not None:
            # a run's stages train on the training views only: its scene holds the test cameras
            cams = {**cams, "test": _run_folder(run)[1]["test"]}
    if ckpt.parent == out_dir:
        remedy = f"delete it and train into {out_dir} again"
    else:  # a run folder's stage (4_ted/<phase>/ckpt.pt, 2_refgs/gs/ckpt.pt)
        remedy = f"rerun coin-cl run on {out_dir} with --force {ckpt.relative_to(out_dir).parts[0]}"
    state = load_checkpoint(ckpt, remedy)
    try:
        model = model_from_state(state["model"])
        step = int(state["trainer"]["step"])
    except (KeyError, TypeError, AttributeError, IndexError) as exc:
        raise malformed(ckpt, exc, remedy) from None
    model.device = device
    if views != "orbit" and not cams.get(views):  # after the checkpoint: a bad one is said first
        raise ValueError(
            f"{out_dir} has no {views} cameras: nothing to render; "
            f"choose --views {'train' if views == 'test' else 'test'} or orbit"
        )
    factor = capture_scale(out_dir) if scale == "capture" else float(scale)
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"scale {scale!r} is not a positive number; give one > 0, or 'capture'")

    def sized(kind: str) -> list:
        return [c.resized(max(1, round(c.width * factor)), max(1, round(c.height * factor)))
                for c in cameras_from_json(cams[kind])]  # fmt: skip

    root = out_dir / "renders" if dest is None else Path(dest)
    dest = root / views
    if views == "orbit":
        gif = root / "orbit.gif"
        train = sized("train")
        orbit = orbit_gif(model, train, gif, frames, step, backend, dest, depth=True)
        return len(orbit), gif
    cameras = sized(views)
    # named as the views (`<stem>.png`), so that `coin-cl eval DEST --scene SCENE` reads them
    names = [Path(c.name).stem if c.name else f"{i:03d}" for i, c in enumerate(cameras)]
    render_views(lambda c: model.render(c, step, backend=backend, return_depth=True),
                 cameras, dest, depth=True, desc=f"{views} views", names=names)  # fmt: skip
    return len(cams[views]), dest
