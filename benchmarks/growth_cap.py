"""Benchmark: Scaffold-GS growth against its size cap (`ScaffoldStrategy.gaussians_per_pixel`).

For each cap (neural Gaussians per training pixel; 0 = no cap) trains the plain Scaffold-GS that
the pipeline's timing probe trains and every GS stage of CoIn grows (default schedule compressed
to `--steps`, `scaled_strategy`) on a scene's captured views, holding out every 8th training view,
from the same initialisation on the same view sequence. Per cap: the cap's count, the model's
largest and final size (neural Gaussians = anchors x 10), held-out PSNR / SSIM after the run,
seconds per early step (steps 5-35, before the first growth: what the probe measures) and per
late step (the last fifth of the run, after growth has stopped), their ratio, and the training
seconds: error next to run time.

    python benchmarks/growth_cap.py [SCENE] [--resolution 0.5] [--steps 800] [--caps 0,0.1,0.2]

`--run RUN` instead trains the Ref-GS stage (`run_refgs`, where growth is worst: the per-view
inpaints disagree inside the masks) on a finished `coin-cl run` folder's working scene
(RUN/0_scene/scene) and stage-1 inpaints (RUN/1_inpaint/images), reusing its depth prior
(RUN/2_refgs/depth_prior.*), and scores the scene's test views (on a virtual-object or SPIn-NeRF
scene, real captures without the object): PSNR over the image and m-PSNR in the mask. Early and
late steps as above (early: before the first growth; late: the last fifth, attention included).

    python benchmarks/growth_cap.py --run RUN [--steps 500] [--caps 0,0.01,0.02] [--parts]

`--parts` (with `--run`) also times every part of a Ref-GS step (decode, projection, binning,
rasterization forward and backward, the loss terms, their `before_render` work such as the anchor
attention, the whole backward, the optimiser, growth) and prints the median of each, early and
late, and their ratio: where a late step's extra time goes.

Ends with one JSON line {"scene", "resolution", "steps", "rows": [...]}.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import cpu_model, git_commit  # noqa: E402

from coin_cl import load_scene  # noqa: E402
from coin_cl.checkpoint import load_checkpoint  # noqa: E402
from coin_cl.gs.data import Camera  # noqa: E402
from coin_cl.gs.model_kinds import model_from_state, scaled_model_config, scaled_strategy  # noqa: E402
from coin_cl.gs.trainer import TrainConfig, evaluate_views, make_trainer  # noqa: E402
from coin_cl.scene.splits import split_indices  # noqa: E402

EARLY = (5, 35)  # steps timed as "early": after warm-up, before the compressed schedule's first growth


def run_cap(scene, cap: float, steps: int, backend: str) -> dict:
    """Train `steps` steps with `gaussians_per_pixel=cap`; sizes, held-out scores and step times."""
    tr_idx, te_idx = split_indices(scene, 8)
    cfg = TrainConfig(model="scaffold", iters=steps, backend=backend, progress=False, ckpt_every=0,
                      export_ply=False, log_every=steps)  # fmt: skip
    strategy = replace(scaled_strategy("scaffold", steps), gaussians_per_pixel=cap)
    tr = make_trainer(scene, tr_idx, te_idx, cfg, None, None, scaled_model_config("scaffold", steps),
                      resume=False, strategy=strategy)  # fmt: skip
    n0 = tr.model.n_primitives
    times, sizes, drawn = [], [], []
    for _ in range(steps):
        t = time.perf_counter()
        rec = tr.train_step()
        times.append(time.perf_counter() - t)
        tr.step += 1
        sizes.append(tr.model.n_primitives)
        drawn.append(rec["n_drawn"])
    ev = evaluate_views(tr.model, tr.test_views, tr.step, backend, tr.background)
    late = slice(steps - steps // 5, steps)
    early_s = float(np.mean(times[EARLY[0] : EARLY[1]]))
    late_s = float(np.mean(times[late]))
    limit = tr.strategy.size_limit(tr.model)
    return {
        "cap_per_pixel": cap,
        "cap": limit["neural_gaussians"] if cap > 0 else None,
        "train_pixels": tr.train_pixels,
        "n_initial": n0,
        "n_peak": max(sizes),
        "n_final": sizes[-1],
        "drawn_early": float(np.mean(drawn[EARLY[0] : EARLY[1]])),  # Gaussians with opacity > 0
        "drawn_late": float(np.mean(drawn[late])),
        "psnr": ev["psnr"],
        "ssim": ev["ssim"],
        "s_step_early": early_s,
        "s_step_late": late_s,
        "late_over_early": late_s / early_s,
        "train_seconds": float(np.sum(times)),
    }


def _part_timer(tr):
    """A `train.PartTimer` on the parts of `tr`'s Ref-GS step (see the module doc, `--parts`)."""
    from train import PartTimer, patch_engine_parts

    pt = PartTimer()
    patch_engine_parts(pt)
    for obj, attr, part in (
        (tr.model, "visible_anchors", "visible anchors"), (tr.model, "decode", "decode"),
        (tr.model, "render", "render (all)"), (torch.Tensor, "backward", "backward (all)"),
        (tr.model.optimizer, "step", "optimizer"), (tr.strategy, "step_post_backward", "growth"),
    ):  # fmt: skip
        pt.patch(obj, attr, part)
    for term in tr.terms:
        pt.patch(type(term), "__call__", f"term {term.name}")
        if hasattr(term, "before_render"):
            pt.patch(type(term), "before_render", f"before_render {term.name}")
    return pt


def run_refgs_cap(run: Path, cap: float, steps: int, backend: str, work: Path, parts: bool = False) -> dict:
    """Ref-GS for `steps` steps on `run`'s working scene and stage-1 inpaints with the cap `cap`;
    sizes, test-view scores and step times (with `parts`, 'parts': {part: (early s, late s)}, the
    median of each part of a step)."""
    import shutil

    from imageio.v2 import imread

    from coin_cl import metrics
    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.pipeline.refgs import run_refgs
    from coin_cl.scene.io import view_stem

    scene = load_scene(run / "0_scene" / "scene")
    targets = [imread(run / "1_inpaint" / "images" / f"{view_stem(scene.cameras[i].name, i)}.png")
               .astype(np.float32)[..., :3] / 255 for i in scene.train_idx]  # fmt: skip
    out = work / f"cap_{cap:g}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for name in ("depth_prior.npy", "depth_prior.json"):  # the run's prior, so no auxiliary GS trains
        if (run / "2_refgs" / name).is_file():
            shutil.copy(run / "2_refgs" / name, out / name)
    times, sizes = [], []
    last = 0.0
    pt = None  # the part timer, made on the first step when `parts`

    def timer(tr, step: int) -> None:
        nonlocal last, pt
        now = time.perf_counter()
        if parts and pt is None:
            pt = _part_timer(tr)
        if step:
            times.append(now - last)
            sizes.append(tr.model.n_primitives)
            if pt is not None:
                pt.lap()
        last = now

    try:
        res = run_refgs(scene, targets, out, RefGSConfig(), budget_minutes=None, iters=steps, backend=backend,
                        ckpt_every=0, callback=timer, gaussians_per_pixel=cap)  # fmt: skip
    finally:
        if pt is not None:
            pt.restore()
    sizes.append(res["n_primitives"])
    gs = json.loads((out / "gs" / "log.json").read_text())
    model = model_from_state(load_checkpoint(out / "gs" / "ckpt.pt")["model"])
    scores = []
    with torch.no_grad():
        for i in scene.test_idx:
            cam = Camera.from_any(scene.cameras[i])
            img = model.render(cam, steps, backend=backend).image.clamp(0, 1).numpy()
            gt = np.asarray(scene.images[i], np.float32)[..., :3]
            scores.append(metrics.evaluate_view(img, gt, np.asarray(scene.masks[i], bool)))
    late = slice(len(times) - len(times) // 5, len(times))
    early_s = float(np.mean(times[EARLY[0] : EARLY[1]]))
    late_s = float(np.mean(times[late]))
    split = {}
    if pt is not None:  # lap i holds step i's parts (the callback runs before each step)
        laps = pt.steps
        names = sorted({k for lap in laps for k in lap})
        split = {k: (float(np.median([lap.get(k, 0.0) for lap in laps[EARLY[0] : EARLY[1]]])),
                     float(np.median([lap.get(k, 0.0) for lap in laps[late]]))) for k in names}  # fmt: skip
    return {
        "cap_per_pixel": cap,
        "cap": gs["strategy"]["size_limit"]["neural_gaussians"] if cap > 0 else None,
        "train_pixels": gs["strategy"]["train_pixels"],
        "n_initial": gs["train"][0]["n"],
        "n_peak": max(sizes),
        "n_final": sizes[-1],
        "psnr": float(np.mean([d["psnr"] for d in scores])),
        "m_psnr": float(np.mean([d["m_psnr"] for d in scores])),
        "ssim": float(np.mean([d["ssim"] for d in scores])),
        "s_step_early": early_s,
        "s_step_late": late_s,
        "late_over_early": late_s / early_s,
        "train_seconds": float(np.sum(times)),
        **({"parts": split} if parts else {}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(ROOT.parent / "shared" / "data" / "spinnerf_scene1"))
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--caps", default="0,0.1,0.2", help="neural Gaussians per training pixel; 0: none")
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--run", type=Path, help="Ref-GS on this coin-cl run folder's stage-1 inpaints")
    ap.add_argument("--work", type=Path, default=Path("growth_cap_out"), help="Ref-GS folders (--run)")
    ap.add_argument("--parts", action="store_true", help="with --run: time each part of a step")
    a = ap.parse_args()
    if a.steps < 5 * EARLY[1]:
        ap.error(f"--steps {a.steps}: use at least {5 * EARLY[1]} (early steps are {EARLY})")
    torch.manual_seed(0)
    scene = None if a.run else load_scene(a.scene, resolution=a.resolution)
    rows = []
    what = f"Ref-GS on {a.run}" if a.run else f"Scaffold-GS on {a.scene} at resolution {a.resolution}"
    print(f"# {what}, {a.steps} steps; {cpu_model()}; {git_commit()}")
    print("| cap / px | cap | initial | peak | final | PSNR | m-PSNR | SSIM | s/step early | late | "
          "late/early | train s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for cap in (float(c) for c in a.caps.split(",")):
        if a.run:
            r = run_refgs_cap(a.run, cap, a.steps, a.backend, a.work, parts=a.parts)
        else:
            r = run_cap(scene, cap, a.steps, a.backend)
        rows.append(r)
        mp = f"{r['m_psnr']:.2f}" if "m_psnr" in r else "-"
        print(f"| {cap:g} | {r['cap'] or 'none'} | {r['n_initial']} | {r['n_peak']} | {r['n_final']} | "
              f"{r['psnr']:.2f} | {mp} | {r['ssim']:.4f} | {r['s_step_early']:.3f} | "
              f"{r['s_step_late']:.3f} | {r['late_over_early']:.2f} | {r['train_seconds']:.0f} |",
              flush=True)  # fmt: skip
    for r in rows:
        if r.get("parts"):
            cap = f"{r['cap_per_pixel']:g}"
            print(f"\n| part of a Ref-GS step, cap {cap} (median ms) | early | late | late / early |")
            print("|---|---|---|---|")
            for k, (e, late) in r["parts"].items():
                print(f"| {k} | {1000 * e:.1f} | {1000 * late:.1f} | {late / e:.2f} |" if e > 0 else
                      f"| {k} | {1000 * e:.1f} | {1000 * late:.1f} | - |")  # fmt: skip
    print(json.dumps({"scene": str(a.run or a.scene), "resolution": None if a.run else a.resolution,
                      "steps": a.steps, "rows": rows}))  # fmt: skip


if __name__ == "__main__":
    main()
