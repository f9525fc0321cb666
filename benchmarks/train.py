"""Benchmark: Gaussian-splatting reconstruction and the naive LaMa-inpaint baseline on SPIn-NeRF.

1. Reconstruction: train each model on the object-present views at half of images_4 (504x284),
   holding out every 8th for evaluation; held-out PSNR/SSIM against training wall-clock.
2. Baseline: train the better model on the dataset's per-view LaMa inpaints (RGB_inpainted/) of all
   34 training views; score the 5 object-absent test views: PSNR, SSIM, m-PSNR, m-SSIM (masks
   from test_label/), and write comparison grids.

Ends with one JSON line: recon_psnr, recon_minutes, baseline_psnr, baseline_mpsnr, baseline_ssim,
model (+ more). Usage:
    python benchmarks/train.py [--minutes 20] [--baseline-minutes 10] [--models scaffold,3dgs]

Training throughput instead: `--throughput` (or `--profile`, the same runs) trains each
model with the unfused path (`TrainConfig(fused=False)`) and the fused one, from the same
initialisation on the same view sequence, `--steps` steps each; prints the median time per step of
every part (anchor decode, project, bin, rasterize, loss, backward, optimiser, densification,
the rest), steps/s and the held-out PSNR after those steps, and ends with one JSON line
(scaffold_steps_s_old/new, gs3d_steps_s_old/new, psnr_old/new, ...):
    python benchmarks/train.py --throughput [--steps 200] [--models scaffold,3dgs] [--discrete]
The run table's "copy MB/step" and "copy ms/step" are the host <-> device copies per step (0 on a
host-unified-memory device; `--discrete` forces the discrete-GPU path, COIN_CL_DISCRETE=1).
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

from common import cpu_model, default_data, git_commit  # noqa: E402
from tqdm import tqdm  # noqa: E402

from coin_cl import load_scene, metrics  # noqa: E402
from coin_cl.gs.model_kinds import scaled_model_config  # noqa: E402
from coin_cl.gs.trainer import TrainConfig, evaluate_views, make_trainer  # noqa: E402
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


class PartTimer:
    """Wall time of named callables per training step: `patch(obj, attr, part)` wraps
    `obj.attr` (restored by `restore`); `lap()` closes a step. Medians make the table robust to
    the odd slow step (a checkpoint, the OS)."""

    def __init__(self) -> None:
        self.now: dict[str, float] = {}
        self.steps: list[dict[str, float]] = []
        self._undo: list = []

    def patch(self, obj, attr: str, part: str) -> None:
        import functools

        f = getattr(obj, attr)

        @functools.wraps(f)
        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                self.now[part] = self.now.get(part, 0.0) + time.perf_counter() - t

        had = attr in vars(obj)
        setattr(obj, attr, timed)
        self._undo.append((obj, attr, f if had else None))

    def restore(self) -> None:
        for obj, attr, f in reversed(self._undo):
            if f is None:
                delattr(obj, attr)
            else:
                setattr(obj, attr, f)
        self._undo.clear()

    def lap(self, **extra: float) -> None:
        self.steps.append({**self.now, **extra})
        self.now = {}

    def median(self, part: str) -> float:
        return float(np.median([s.get(part, 0.0) for s in self.steps])) if self.steps else 0.0


# Parts of a step, in table order; 'torch backward' is the autograd time outside the two kernels'
# backward (decode / activations, loss), 'other' the step's wall time minus everything listed.
PARTS = ("visible anchors", "decode / activations", "project fwd", "bin", "rasterize fwd", "loss fwd",
         "rasterize bwd", "project bwd", "torch backward", "optimizer", "densification")  # fmt: skip


def patch_engine_parts(pt: PartTimer) -> None:
    """Time the engine's parts of any GS step on `pt`: the projection and rasterization kernels'
    forward and backward, tile binning and the photometric loss's map."""
    import importlib

    from coin_cl.gs import terms as gs_terms

    # The modules, not the functions `coin_cl.engine.ops` re-exports under the same names.
    ops_project = importlib.import_module("coin_cl.engine.ops.project")
    ops_raster = importlib.import_module("coin_cl.engine.ops.rasterize")
    pt.patch(ops_raster._Rasterize, "forward", "rasterize fwd")
    pt.patch(ops_raster._Rasterize, "backward", "rasterize bwd")
    pt.patch(ops_project._Project, "forward", "project fwd")
    pt.patch(ops_project._Project, "backward", "project bwd")
    pt.patch(ops_raster, "bin_tiles", "bin")
    pt.patch(gs_terms, "photometric_map", "loss fwd")


def speed_run(scene, kind: str, fused: bool, steps: int, warmup: int, backend: str) -> dict:
    """Train `kind` for warmup + `steps` steps on `fused` or the unfused path; per-part medians,
    steps/s over the timed steps, held-out PSNR at the end."""
    from coin_cl.engine import rendering
    from coin_cl.engine.runtime import resolve_device

    tr_idx, te_idx = split_indices(scene, 8)
    # A 3000-step schedule, so densification is active as in a real run.
    # A checkout older than the fused path has no `fused` switch: its one path is the unfused one.
    path = {"fused": fused} if "fused" in TrainConfig.__dataclass_fields__ else {}
    cfg = TrainConfig(model=kind, iters=3000, backend=backend, ckpt_every=0, progress=False,
                      export_ply=False, **path)  # fmt: skip
    tr = make_trainer(scene, tr_idx, te_idx, cfg, None, None, scaled_model_config(kind, 3000),
                      resume=False)  # fmt: skip
    m = tr.model
    rt = resolve_device(None)
    pt = PartTimer()
    patch_engine_parts(pt)
    pt.patch(rendering, "finite_rows", "finite check")
    pt.patch(m.optimizer, "step", "optimizer")
    pt.patch(tr.strategy, "step_pre_backward", "densification")
    pt.patch(tr.strategy, "step_post_backward", "densification")
    if kind == "scaffold":
        pt.patch(m, "visible_anchors", "visible anchors")
        pt.patch(m, "decode", "decode / activations")
    else:
        pt.patch(m, "render", "render")  # activations = render - project - bin - rasterize fwd
    try:
        for _ in range(warmup):  # kernel builds and first-touch allocations
            tr.train_step()
            tr.step += 1
        pt.steps.clear()
        pt.now = {}
        n_programs, copies0 = len(rt.programs), rt.transfers.snapshot()
        t0 = time.perf_counter()
        for _ in tqdm(range(steps), desc=f"{kind} {'fused' if fused else 'unfused'}", leave=False,
                      disable=not sys.stderr.isatty()):  # fmt: skip
            t = time.perf_counter()
            r = tr.train_step()
            tr.step += 1
            pt.lap(total=time.perf_counter() - t, t_bwd=r["t_bwd"], n_drawn=r["n_drawn"])
        wall = time.perf_counter() - t0
    finally:
        pt.restore()
    med = {p: pt.median(p) for p in (*PARTS, "finite check", "render", "total", "t_bwd")}
    if kind != "scaffold":
        med["decode / activations"] = max(
            0.0, med["render"] - med["project fwd"] - med["bin"] - med["rasterize fwd"] - med["finite check"]
        )
    med["torch backward"] = max(0.0, med["t_bwd"] - med["rasterize bwd"] - med["project bwd"])
    med["other"] = max(0.0, med["total"] - sum(med[p] for p in PARTS) - med["finite check"])
    res = evaluate_views(m, tr.test_views, tr.step, backend, tr.background)
    return {
        "model": kind, "fused": fused, "steps": steps, "steps_s": steps / wall,
        "ms_per_step": 1000 * wall / steps, "median_ms": {k: 1000 * v for k, v in med.items()},
        "psnr": res["psnr"], "ssim": res["ssim"], "n_primitives": m.n_primitives,
        "n_drawn_median": pt.median("n_drawn"), "programs_built": len(rt.programs) - n_programs,
        "bytes_host_device": rt.bytes_transferred - copies0["bytes"],
        "copy_ms_per_step": 1000 * (rt.transfers.seconds - copies0["seconds"]) / steps,
        "copy_mb_per_step": (rt.bytes_transferred - copies0["bytes"]) / 1e6 / steps,
    }  # fmt: skip


def speed(args, scene) -> int:
    w, h = scene.cameras[0].width, scene.cameras[0].height
    from coin_cl.engine.runtime import resolve_device

    rt = resolve_device(None)
    runs: dict[str, dict] = {}
    for kind in args.models.split(","):
        for fused in [p == "new" for p in args.paths.split(",")]:
            key = f"{kind}_{'new' if fused else 'old'}"
            runs[key] = speed_run(scene, kind, fused, args.steps, args.warmup, args.backend)
            print(f"{key}: {runs[key]['steps_s']:.2f} steps/s, PSNR {runs[key]['psnr']:.2f}", file=sys.stderr)
    print(f"\n# training throughput, SPIn-NeRF scene 1 at {w}x{h}: {cpu_model()}, {os.cpu_count()} "
          f"cores; {rt.name} ({'discrete' if rt.discrete else 'unified'} memory path); commit "
          f"{git_commit()}; {args.steps} timed steps after {args.warmup} warm-up")  # fmt: skip
    keys = list(runs)
    print("\n| part (median ms per step) | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for part in (*PARTS, "finite check", "other", "total"):
        cells = []
        for k in keys:
            ms = runs[k]["median_ms"][part]
            share = 100 * ms / max(runs[k]["median_ms"]["total"], 1e-9)
            cells.append(f"{ms:.1f} ({share:.0f}%)")
        print(f"| {part} | " + " | ".join(cells) + " |")
    print("\n| run | steps/s | ms/step | held-out PSNR | SSIM | primitives | drawn (median) | kernel builds "
          "| host<->device bytes | copy MB/step | copy ms/step |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k, r in runs.items():
        print(f"| {k} | {r['steps_s']:.2f} | {r['ms_per_step']:.0f} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
              f"{r['n_primitives']} | {r['n_drawn_median']:.0f} | {r['programs_built']} | "
              f"{r['bytes_host_device']} | {r['copy_mb_per_step']:.2f} | "
              f"{r['copy_ms_per_step']:.2f} |")  # fmt: skip
    result: dict = {"cpu": cpu_model(), "device": rt.name, "commit": git_commit(), "resolution": [w, h],
                    "steps": args.steps, "discrete": rt.discrete}  # fmt: skip
    for k, r in runs.items():
        result[f"{k}_copy_ms_per_step"] = round(r["copy_ms_per_step"], 3)
    for kind, tag in (("scaffold", "scaffold"), ("3dgs", "gs3d")):
        for path in ("old", "new"):
            r = runs.get(f"{kind}_{path}")
            if r is not None:
                result[f"{tag}_steps_s_{path}"] = round(r["steps_s"], 3)
                result[f"{tag}_psnr_{path}"] = round(r["psnr"], 3)
        if f"{kind}_old" in runs and f"{kind}_new" in runs:
            ratio = runs[f"{kind}_new"]["steps_s"] / runs[f"{kind}_old"]["steps_s"]
            result[f"{tag}_speedup"] = round(ratio, 3)
    first = args.models.split(",")[0]
    result["psnr_old"] = result.get(f"{'gs3d' if first == '3dgs' else first}_psnr_old")
    result["psnr_new"] = result.get(f"{'gs3d' if first == '3dgs' else first}_psnr_new")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "throughput.json").write_text(json.dumps({"result": result, "runs": runs}, indent=1))
    print(json.dumps(result))
    return 0


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
    ap.add_argument("--throughput", action="store_true", help="old vs fused path: steps/s, profile, PSNR")
    ap.add_argument("--profile", action="store_true", help="the same runs as --throughput")
    ap.add_argument("--steps", type=int, default=200, help="timed steps per run (--throughput)")
    ap.add_argument("--warmup", type=int, default=5, help="untimed steps first (--throughput)")
    ap.add_argument("--paths", default="old,new", help="which training paths (--throughput)")
    ap.add_argument(
        "--discrete",
        action="store_true",
        help="device-only buffers and counted copies, as on a discrete GPU (COIN_CL_DISCRETE=1)",
    )
    args = ap.parse_args()
    if args.discrete:  # before the first runtime is made
        os.environ["COIN_CL_DISCRETE"] = "1"

    scene = load_scene(args.data, resolution=args.resolution)
    if args.throughput or args.profile:
        return speed(args, scene)
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
