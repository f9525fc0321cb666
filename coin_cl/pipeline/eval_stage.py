"""The eval stage (paper 5): renders of the test and training views, the orbit GIF, the final PLY,
and the metrics against ground truth where the scene has object-absent test views
(`coin_cl.evaluation`).

A run trains at a working resolution below the capture's (`coin_cl.pipeline.budget`); its metrics are
scored there (eval/metrics) and, where the working size is smaller, once more on the test views
rendered at the capture's own size against the captured photos (eval/capture): a small working
size pays for its blur in the second figure.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from coin_cl.pipeline.runner import StageContext, jsonable
from coin_cl.pipeline.stages import load_model

if TYPE_CHECKING:
    from coin_cl.pipeline.run_inputs import CaptureViews, RunInputs

# The folder under the eval stage that holds the capture-size renders and their metrics.
CAPTURE_DIR = "capture"


def score_at_capture(model, views: CaptureViews, out: Path) -> dict:
    """Render `model` at each of `views`' cameras (the capture's size), write out/renders/<stem>.png
    and score them against the photos (`coin_cl.evaluation.score_views`: out/metrics.json). Returns
    the metrics document."""
    import torch

    from coin_cl.evaluation import score_views
    from coin_cl.scene.io import to_uint8, write_png

    rdir = Path(out) / "renders"
    rdir.mkdir(parents=True, exist_ok=True)
    scored = {}
    for i, cam in views.cameras.items():
        with torch.no_grad():
            r = model.render(cam, 10**9)
        img = to_uint8(r.image.clamp(0, 1).numpy())
        write_png(rdir / f"{Path(cam.name).stem}.png", img)
        # scored as written (8 bits), as the working-resolution renders are
        scored[cam.name] = (img.astype(np.float32) / 255.0, views.images[i], views.masks[i])
    return score_views(scored, out)


def stage_eval(ctx: StageContext[RunInputs]) -> dict:
    import torch

    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.scene.io import to_uint8, write_npy, write_png

    scene = ctx.run.scene
    cfg = ctx.run.cfg
    final = ctx.settings["final"]
    folder = [p for n, p in ctx.inputs.items() if n == final][0]
    model = load_model(folder, CKPT_NAME, model_from_state)
    model.device = cfg.device
    rdir, ddir = ctx.out / "renders", ctx.out / "depths"
    rdir.mkdir(parents=True, exist_ok=True)
    ddir.mkdir(parents=True, exist_ok=True)

    from tqdm import tqdm

    views = list(scene.test_idx) + list(scene.train_idx)
    for i in tqdm(views, desc="eval renders", unit="view"):
        with torch.no_grad():
            r = model.render(scene.cameras[i], 10**9, return_depth=True)
        stem = Path(scene.cameras[i].name).stem
        write_png(rdir / f"{stem}.png", to_uint8(r.image.clamp(0, 1).numpy()))
        if i in scene.test_idx:  # camera z where the render is opaque (the depth grid, the ghost figure)
            d = r.depth.numpy().astype(np.float32)
            write_npy(ddir / f"{stem}.npy", np.where(r.alpha.numpy() > 0.5, d, np.nan))
    from coin_cl.render_utils import orbit_gif

    orbit_gif(model, [scene.cameras[i] for i in scene.train_idx], ctx.out / "orbit.gif")
    ply = ctx.out / "point_cloud.ply"
    centers = torch.stack([scene.cameras[i].center_t for i in scene.train_idx])
    # SH padded to degree 3 (the record graphdeco's SIBR reads); NaN/Inf Gaussians left out, counted
    dropped = model.export_gaussians(centers.mean(0)).to_ply(ply)
    result: dict[str, Any] = {"final_stage": final, "ply": str(ply), "ply_nonfinite_dropped": dropped}
    gt_ok = scene.test_idx and all(scene.masks[i].any() for i in scene.test_idx)
    if gt_ok:
        from coin_cl.evaluation import evaluate_folder

        doc = evaluate_folder(rdir, ctx.inputs["0_scene"] / "scene", ctx.out / "metrics",
                              split_dir=ctx.inputs.get("0_refine"), depth_dir=ddir)  # fmt: skip
        result["metrics"] = doc["mean"]
        if doc["vgg_pd"] != "available":  # the run's log says why the VGG-PD columns are n/a
            ctx.note(doc["vgg_pd"])
        if ctx.run.capture is not None:
            cdoc = score_at_capture(model, ctx.run.capture, ctx.out / CAPTURE_DIR)
            result["metrics_capture"] = cdoc["mean"]
            m = cdoc["mean"]
            ctx.note(f"at the capture's resolution: m-PSNR {m['m_psnr']:.2f}, m-VGG-PD "
                     f"{m['m_vgg_pd'] if m['m_vgg_pd'] is None else round(m['m_vgg_pd'], 3)} "
                     f"({ctx.out / CAPTURE_DIR})")  # fmt: skip
    else:
        ctx.note("no ground-truth test views with masks: metrics skipped")
    return jsonable(result)
