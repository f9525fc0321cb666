"""Benchmark: Gaussian-splatting reconstruction and the naive LaMa-inpaint baseline on SPIn-NeRF.

1. Reconstruction: train each model on the object-present views at half of images_4 (504x284),
   holding out every 8th for evaluation; held-out PSNR/SSIM against training wall-clock.
2. Baseline: train the better model on the dataset's per-view LaMa inpaints (RGB_inpainted/) of all
   34 training views; score the 5 object-absent test views: PSNR, SSIM, m-PSNR, m-SSIM (masks
   from test_label/), and write comparison grids.

Ends with one JSON line: recon_psnr, recon_minutes, baseline_psnr, baseline_mpsnr, baseline_ssim,
model (+ more). Usage:
    python benchmarks/train.py [--minutes 20] [--baseline-minutes 10] [--models scaffold,3dgs]
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import default_data, git_commit  # noqa: E402

from coin_cl import load_scene, metrics  # noqa: E402
from coin_cl.gs.trainer import TrainConfig, make_trainer, scaled_model_config  # noqa: E402
from coin_cl.scene.splits import inpainted_targets, split_indices  # noqa: E402

# Steps per second measured over 5-minute runs at 504x284 on the 2-core machine (2026-11-22), used
# only to size each model's schedule to the time budget.
STEPS_PER_SECOND = {"scaffold": 1.25, "3dgs": 1.6}
EVAL_MARKS_MIN = (0.5, 1, 2, 5, 10, 15, 20, 30)


def run_recon(scene, kind: str, minutes: float, iters: int | None, out: Path, backend: str) -> dict:
    n = iters or max(200, int(STEPS_PER_SECOND[kind] * minutes * 60))
    tr_idx, te_idx = split_indices(scene, 8)
    marks = tuple(60.0 * m for m in EVAL_MARKS_MIN if m < minutes)
    cfg = TrainConfig(model=kind, iters=n, backend=backend, max_seconds=60.0 * minutes,
                      eval_at_seconds=marks, ckpt_every=500, progress=sys.stderr.isatty())  # fmt: skip
    tr = make_trainer(scene, tr_idx, te_idx, cfg, out, None, scaled_model_config(kind, n),
                      resume=False)  # fmt: skip
    t = time.perf_counter()
    res = tr.train()
    curve = [{"minutes": e["train_seconds"] / 60, "step": e["step"], "psnr": e["psnr"],
              "ssim": e["ssim"], "n": e["n"]} for e in tr.log["eval"]]  # fmt: skip
    return {"model": kind, "iters_planned": n, "steps": res["step"], "psnr": res["psnr"],
            "ssim": res["ssim"], "minutes": res["train_seconds"] / 60, "n": res["n"],
            "wall_minutes": (time.perf_counter() - t) / 60, "curve": curve,
            "peak_rss_mb": tr.log.get("peak_rss_mb"), "n_train": len(tr_idx),
            "n_eval": len(te_idx)}  # fmt: skip


def run_baseline(scene, kind: str, minutes: float, iters: int | None, out: Path,
                 backend: str) -> dict:  # fmt: skip
    n = iters or max(200, int(STEPS_PER_SECOND[kind] * minutes * 60))
    cfg = TrainConfig(model=kind, iters=n, backend=backend, max_seconds=60.0 * minutes,
                      ckpt_every=500, progress=sys.stderr.isatty())  # fmt: skip
    tr = make_trainer(scene, scene.train_idx, scene.test_idx, cfg, out, inpainted_targets(scene),
                      scaled_model_config(kind, n), resume=False)  # fmt: skip
    res = tr.train()
    import imageio.v2 as imageio

    from coin_cl.scene.io import to_uint8

    per_view = []
    grids = out / "grids"
    grids.mkdir(exist_ok=True)
    for v, i in zip(tr.test_views, scene.test_idx, strict=True):
        with torch.no_grad():
            img = tr.model.render(v.camera, tr.step, backend=backend).image.clamp(0, 1).numpy()
        gt = v.image.numpy()
        mask = np.asarray(scene.masks[i], bool)
        m = metrics.evaluate_view(img, gt, mask)
        per_view.append({"view": scene.cameras[i].name, **{k: m[k] for k in
                         ("psnr", "ssim", "m_psnr", "m_ssim")}})  # fmt: skip
        # Grid: ground truth | render | render with the scored region outlined | |error| x 4.
        import cv2

        outline = to_uint8(img).copy()
        cnts, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(outline, cnts, -1, (255, 0, 0), 1)
        err = to_uint8(np.clip(np.abs(img - gt) * 4, 0, 1))
        imageio.imwrite(grids / f"{Path(scene.cameras[i].name).stem}.png",
                        np.concatenate([to_uint8(gt), to_uint8(img), outline, err], 1))  # fmt: skip
    agg = metrics.aggregate([{k: v for k, v in d.items() if k != "view"} for d in per_view])
    return {"model": kind, "steps": res["step"], "minutes": res["train_seconds"] / 60,
            "n": res["n"], **agg, "per_view": per_view,
            "peak_rss_mb": tr.log.get("peak_rss_mb")}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--minutes", type=float, default=20.0, help="training time per model (recon)")
    ap.add_argument("--baseline-minutes", type=float, default=10.0)
    ap.add_argument("--models", default="scaffold,3dgs")
    ap.add_argument("--iters", type=int, default=0, help="schedule length (default: from time)")
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "train")
    ap.add_argument("--skip-baseline", action="store_true")
    args = ap.parse_args()

    scene = load_scene(args.data, resolution=args.resolution)
    w, h = scene.cameras[0].width, scene.cameras[0].height
    args.out.mkdir(parents=True, exist_ok=True)
    recon = {}
    for kind in args.models.split(","):
        recon[kind] = run_recon(scene, kind, args.minutes, args.iters or None,
                                args.out / f"recon_{kind}", args.backend)  # fmt: skip
    best = max(recon.values(), key=lambda r: r["psnr"])
    base = None
    if not args.skip_baseline:
        base = run_baseline(scene, best["model"], args.baseline_minutes, args.iters or None,
                            args.out / f"baseline_{best['model']}", args.backend)  # fmt: skip

    print(f"\nSPIn-NeRF scene 1 at {w}x{h}; commit {git_commit()}; {platform.machine()} "
          f"{os.cpu_count()} cores; backend {args.backend}")  # fmt: skip
    print("\n| model | train min | step | held-out PSNR | SSIM | primitives |")
    print("|---|---|---|---|---|---|")
    for r in recon.values():
        for c in r["curve"]:
            print(f"| {r['model']} | {c['minutes']:.2f} | {c['step']} | {c['psnr']:.2f} | "
                  f"{c['ssim']:.4f} | {c['n']} |")  # fmt: skip
    if base is not None:
        print("\n| baseline (LaMa inpaints) | model | train min | PSNR | SSIM | m-PSNR | m-SSIM |")
        print("|---|---|---|---|---|---|---|")
        for d in base["per_view"]:
            print(f"| {d['view']} | {base['model']} | | {d['psnr']:.2f} | {d['ssim']:.4f} | "
                  f"{d['m_psnr']:.2f} | {d['m_ssim']:.4f} |")  # fmt: skip
        print(f"| mean | {base['model']} | {base['minutes']:.2f} | {base['psnr']:.2f} | "
              f"{base['ssim']:.4f} | {base['m_psnr']:.2f} | {base['m_ssim']:.4f} |")  # fmt: skip
    result = {
        "recon_psnr": best["psnr"],
        "recon_ssim": best["ssim"],
        "recon_minutes": best["minutes"],
        "recon_steps": best["steps"],
        "model": best["model"],
        "recon_all": {
            k: {
                "psnr": r["psnr"],
                "ssim": r["ssim"],
                "minutes": r["minutes"],
                "steps": r["steps"],
                "peak_rss_mb": r["peak_rss_mb"],
            }
            for k, r in recon.items()
        },  # fmt: skip
        "baseline_psnr": None if base is None else base["psnr"],
        "baseline_ssim": None if base is None else base["ssim"],
        "baseline_mpsnr": None if base is None else base["m_psnr"],
        "baseline_mssim": None if base is None else base["m_ssim"],
        "baseline_minutes": None if base is None else base["minutes"],
        "resolution": [w, h],
        "commit": git_commit(),
    }
    (args.out / "result.json").write_text(json.dumps({"result": result, "recon": recon,
                                                      "baseline": base}, indent=1))  # fmt: skip
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
