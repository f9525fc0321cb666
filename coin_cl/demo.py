"""The demo behind `coin-cl demo`: the engine on a procedural scene (a turntable), and the current
pipeline on the synthetic room with ground truth (the masked-reconstruction baseline)."""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

log = logging.getLogger("coin_cl.demo")


def run_demo(
    out: Path,
    frames: int = 12,
    size: tuple[int, int] = (480, 320),
    steps: int = 400,
    render_only: bool = False,
    device=None,
) -> dict:
    """Part 1: render a procedural Gaussian scene (the engine). Part 2: the synthetic room with
    ground truth: reconstruct it from object-present views with the object masked out of the loss,
    render the object-absent test views and score them. Writes `out/demo.json` (the returned
    summary), `out/turntable/` and `out/room/`. `device`: a runtime or an OpenCL device name."""
    from coin_cl.engine.runtime import resolve_device
    from coin_cl.scene.io import write_text

    rt = resolve_device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"device": rt.name, "turntable": turntable(out / "turntable", frames, size, rt)}
    if not render_only:
        summary["room"] = room_baseline(out / "room", steps, device)
    write_text(out / "demo.json", json.dumps(summary, indent=2))
    return summary


def turntable(out: Path, frames: int = 12, size: tuple[int, int] = (480, 320), device=None) -> dict:
    """Render `frames` views of `coin_cl.scene.procedural.embedded_scene` on a circle: PNG frames
    and `turntable.gif` under `out`; returns timings and pair counts."""
    import imageio.v3 as iio
    import torch
    from tqdm import tqdm

    import coin_cl
    from coin_cl.engine.runtime import resolve_device
    from coin_cl.scene.io import atomic_write, write_png
    from coin_cl.scene.procedural import embedded_scene, turntable_viewmat

    rt = resolve_device(device)
    W, H = size
    gs = embedded_scene()
    f = 0.9 * W
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    out.mkdir(parents=True, exist_ok=True)
    log.info("demo: embedded procedural scene, %d Gaussians, %dx%d, device %s", len(gs.means), W, H, rt.name)
    images, times, pairs = [], [], []
    for i in tqdm(range(frames), desc="rendering turntable"):
        vm = turntable_viewmat(2 * math.pi * i / frames)
        t0 = time.perf_counter()
        img, alpha, depth, meta = coin_cl.rasterize(
            *gs.tensors(),
            vm,
            K,
            W,
            H,
            background=torch.tensor([0.06, 0.07, 0.1]),
            return_depth=True,
            device=rt,
        )
        times.append(time.perf_counter() - t0)
        pairs.append(meta["n_pairs"])
        frame = (img.clamp(0, 1) * 255).to(torch.uint8).numpy()
        images.append(frame)
        write_png(out / f"frame_{i:03d}.png", frame)
    atomic_write(
        out / "turntable.gif", lambda p: iio.imwrite(p, images, extension=".gif", duration=80, loop=0)
    )
    return {
        "gaussians": len(gs.means),
        "size": [W, H],
        "frames": frames,
        "median_render_s": sorted(times)[len(times) // 2],
        "median_pairs": sorted(pairs)[len(pairs) // 2],
    }


def room_baseline(out: Path, steps: int = 400, device=None) -> dict:
    """The synthetic room: 3DGS trained on the object-present views with the object masked out of the
    loss, the object-absent test views rendered into `out/pred` and scored into `out/eval`."""
    import torch

    from coin_cl import load_scene
    from coin_cl.evaluation import evaluate_folder
    from coin_cl.gs.trainer import TrainConfig, make_trainer, scaled_model_config
    from coin_cl.scene.io import to_uint8, write_png
    from coin_cl.scene.synthetic import write_synthetic

    log.info(
        "demo: synthetic room; 3DGS trained on the object-present views with the object masked out "
        "of the loss (the masked-reconstruction baseline; CoIn's inpainting stages are not in this "
        "version), scored on the object-absent ground-truth views"
    )
    scene_dir = out / "scene"
    if not (scene_dir / "views.txt").is_file():
        write_synthetic(scene_dir, coverage=180, n_views=24, width=192, height=144, seed=0)
    scene = load_scene(scene_dir)
    cfg = TrainConfig(model="3dgs", iters=steps, ckpt_every=200)
    trainer = make_trainer(
        scene, scene.train_idx, scene.test_idx, cfg, out / "train",
        model_cfg=scaled_model_config("3dgs", steps), exclude_masks=True, device=device,
    )  # fmt: skip
    res = trainer.train()
    pred = out / "pred"
    pred.mkdir(parents=True, exist_ok=True)
    for view in trainer.test_views:
        with torch.no_grad():
            r = trainer.model.render(view.camera, trainer.step)
        write_png(pred / view.camera.name, to_uint8(r.image.clamp(0, 1).numpy()))
    doc = evaluate_folder(pred, scene_dir, out / "eval")
    agg = doc["mean"]
    return {
        "steps": res["step"],
        "train_s": res["train_seconds"],
        "gaussians": res["n"],
        "test_psnr": agg.get("psnr"),
        "test_m_psnr": agg.get("m_psnr"),
        "what": "masked-reconstruction baseline (object pixels excluded from the loss)",
    }
