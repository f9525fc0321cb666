"""Benchmark: CoIn end to end beside the naive baseline and the paper's ablations, on the
shared SPIn-NeRF scene at half of images_4, scored on the object-absent ground-truth test views.

Rows (each a `coin_cl.inpaint` run folder under --out; a row starts from the `coin` row's stage
folders, and the stage runner keeps exactly those whose settings and inputs match, so rows share
work without any row-specific bookkeeping):
    default      exactly what a user's first command does: `coin-cl run DATA --out DIR`, no other flag
                 (working resolution, timing probe and plan chosen by coin-cl)
    default_baseline  the naive baseline at the default row's resolution and budget: as many
                 Scaffold-GS steps as the default row trained (Ref-GS + TE-D; `demo.baseline_config`)
    coin         the full pipeline, seg masks, the dataset's LaMa inpaints as initial 2D results
    baseline     naive: plain Scaffold-GS on the same initial inpaints (no Ref-GS, CLG, TE-D), as many
                 steps as the coin row trained (Ref-GS + TE-D) when that row ran first
    no_refgs     w/o Ref-GS (plain Scaffold-GS in stage 2, then CLG and TE-D)
    no_weights   w/o the adaptive view weights of Ref-GS
    no_attn      w/o the anchor feature attention of Ref-GS
    no_clg       w/o CLG (TE-D fine-tunes on the initial inpaints)
    no_ted       w/o TE-D (the Ref-GS scene is the result)
    seg_prior    the full pipeline, seg masks, initial inpaints from the embedded scene prior
    bbox         the full pipeline, bounding-box masks (initial inpaints from the scene prior: the
                 LaMa inpaints were made for the segmentation)
Every figure: PSNR, SSIM, m-PSNR, m-SSIM, the high-frequency ratio in the mask (1 is right, below 1
is blur) and GMSD on the mask's bounding box (`coin_cl.evaluation`), the ghost figure (the
share of the test masks rendered more than 10 % in front of a GS fitted to the object-absent test
views; `benchmarks/ghost.py`), and minutes per stage.

The embedded defaults replace the paper's models (no weights can be downloaded here): the scene
prior stands in for Stable Diffusion 2 (rows seg_prior, bbox), analytic features for DINO (CLG).
`--refs N` adds reference-robustness rows: `ref_<view>`, the coin row with N - 1 other
training views as the reference (random, `--seed`), reported as mean and standard deviation with
the coin row.

Beside the scores, the texture each stage hands to the next (initial inpaints, CLG images, renders)
against the ground truth's, inside the masks (`texture_by_stage`); `--texture-only` prints that table
for rows already run under --out without running anything.

Ends with one JSON line (baseline_mpsnr, coin_mpsnr, ..., floors). Usage:
    python benchmarks/coin.py [--budget 30] [--rows coin,baseline,...] [--resolution 0.5] [--refs 3]

`--only insertion` runs the insertion rows instead, on synthetic rooms with exact ground truth
(insertion from an edited view, refined masks, scribbles, `--refs N` reference robustness; see
benchmarks/coin_insertion.py); none of the rows above run then:
    python benchmarks/coin.py --only insertion [--size 96x72] [--views 16] [--iters 300] [--refs 3]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import (  # noqa: E402
    cpu_model,
    default_data,
    git_commit,
    mean_std,
    other_references,
    vgg_pd_cell,
    vgg_pd_note,
    write_result,
)

from coin_cl import load_scene  # noqa: E402
from coin_cl.demo import baseline_config  # noqa: E402
from coin_cl.gs.refgs import RefGSConfig  # noqa: E402
from coin_cl.pipeline.coin import STAGES, CoInConfig, inpaint  # noqa: E402
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig  # noqa: E402
from coin_cl.pipeline.runner import share_stages  # noqa: E402

ROWS = {
    "default": {},  # run through the CLI, see run_default
    "default_baseline": {},  # see run_default
    "coin": {},
    "baseline": {"skip": ("refgs", "clg", "ted"), "inpaint_region": "input"},
    "no_refgs": {"skip": ("refgs",)},
    "no_weights": {"refgs": RefGSConfig(adaptive_weights=False)},
    "no_attn": {"refgs": RefGSConfig(feature_attention=False)},
    "no_clg": {"skip": ("clg",)},
    "no_ted": {"skip": ("ted",)},
    "seg_prior": {"inpaint2d": Inpaint2DConfig(use_dataset=False)},
    "bbox": {"mask_kind": "bbox"},
    "scribble": {"mask_kind": "scribble"},
    "refined": {"inpaint_region": "refined"},
}
KEYS = ("psnr", "ssim", "m_psnr", "m_ssim", "hf_ratio", "bbox_gmsd", "vgg_pd", "m_vgg_pd")


def row_ghost(run: Path, data: Path) -> float | None:
    """The ghost figure of a row's final model (`benchmarks/ghost.py`; reference: a GS fitted to the
    scene's object-absent test views, cached), or None when the scene has no test view with a mask."""
    from ghost import ghost_of_run, reference_depths

    plan = json.loads((run / "plan.json").read_text()) if (run / "plan.json").is_file() else {}
    scale = (plan.get("key") or {}).get("resolution") or 0.5
    scene = load_scene(data, resolution=scale)
    if not any(np.asarray(scene.masks[i]).any() for i in scene.test_idx):
        return None
    depths = reference_depths(scene, ROOT / "benchmarks" / "out" / "ghost_reference" / f"r{scale}_i600")
    return ghost_of_run(run, scene, depths)["ghost"]


def run_row(name: str, data: Path, out: Path, cfg: CoInConfig) -> dict:
    row_out = out / name
    if name != "coin" and (out / "coin").is_dir():
        share_stages(out / "coin", row_out, STAGES)
    t = time.perf_counter()
    res = inpaint(data, row_out, config=cfg)
    minutes = {k: r.get("seconds", 0.0) / 60 for k, r in res.stages.items()}
    # What each stage took when it ran, in this invocation or the one that made its folder (a
    # rerun that finds everything up to date still reports the row's cost).
    cost = {k: (r.get("seconds") or r.get("seconds_when_run") or 0.0) / 60 for k, r in res.stages.items()}
    m = res.metrics or {}
    return {
        **{k: m.get(k) for k in KEYS},
        "ghost": row_ghost(row_out, data),
        "wall_minutes": (time.perf_counter() - t) / 60,
        "stage_minutes": minutes,
        "cost_minutes": sum(cost.values()),
        "stage_cost_minutes": cost,
        "status": {k: r["status"] for k, r in res.stages.items()},
        "sources": res.stages["1_inpaint"].get("result", {}).get("sources"),
    }


def run_default(data: Path, out: Path, budget: float) -> dict[str, dict]:
    """The `default` row (the CLI with no flag but --budget when it is not the default 30) and the
    `default_baseline` row: plain Scaffold-GS on the same initial inpaints, at the default row's
    resolution and budget (as many GS steps as it trained, `demo.baseline_config`), sharing its
    stages 0 and 1 (0_refine too where the default ran it)."""
    import subprocess

    row_out = out / "default"
    cmd = ["coin-cl", "run", str(data), "--out", str(row_out)] + (
        [] if budget == 30.0 else ["--budget", str(budget)]
    )
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    t = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = (time.perf_counter() - t) / 60
    logd = json.loads((row_out / "log.json").read_text())["stages"]
    plan = json.loads((row_out / "plan.json").read_text())
    metrics = json.loads((row_out / "eval" / "metrics" / "metrics.json").read_text())["mean"]
    cost = {k: (r.get("seconds") or r.get("seconds_when_run") or 0.0) / 60 for k, r in logd.items()}
    rows = {"default": {**{k: metrics.get(k) for k in KEYS}, "ghost": row_ghost(row_out, data),
                        "wall_minutes": wall,
                        "stage_minutes": {k: r.get("seconds", 0.0) / 60 for k, r in logd.items()},
                        "cost_minutes": sum(cost.values()), "stage_cost_minutes": cost,
                        "status": {k: r["status"] for k, r in logd.items()}, "plan": plan,
                        "resolution": plan["key"]["resolution"]}}  # fmt: skip
    # The default run's own config (what the CLI resolved), so stages 0-1 are reused as they are.
    cfg = baseline_config(CoInConfig(budget_minutes=budget, resolution=plan["key"]["resolution"]), row_out)
    share_stages(row_out, out / "default_baseline", ("0_scene", "0_refine", "1_inpaint"))
    rows["default_baseline"] = run_row("default_baseline", data, out, cfg)
    return rows


def steps_from(run: Path, base: CoInConfig) -> CoInConfig:
    """`base` with the resolution, step counts (`schedule.run_steps`: TE-D's as the run re-planned
    them), Ref-GS's schedule span (`CoInConfig.refgs_schedule_iters`, from its training log), the
    steps of the auxiliary GS behind its depth prior (`RefGSConfig.depth_prior_iters`, where the run
    trained one and `base` leaves it None: the default derives it from Ref-GS's count before that is
    planned again) and scene prior seconds of the run folder `run`, given explicitly: the run's
    training again."""
    from coin_cl.pipeline.budget import PLAN_FILE
    from coin_cl.pipeline.schedule import run_steps

    try:
        st = run_steps(run)
    except FileNotFoundError as exc:
        raise SystemExit(f"--steps-from: {exc} (pass a finished run folder, e.g. OUT/default)") from None
    plan = json.loads((run / PLAN_FILE).read_text())
    print(f"schedule from {run}: {st}, scene prior {plan['prior_seconds']:.0f} s, "
          f"resolution {plan['key']['resolution']}", file=sys.stderr, flush=True)  # fmt: skip
    span = None
    refgs_log = run / "2_refgs" / "gs" / "log.json"
    if refgs_log.is_file():
        span = json.loads(refgs_log.read_text()).get("refgs", {}).get("schedule_iters")
    refgs = base.refgs
    aux_log = run / "2_refgs" / "aux_gs" / "log.json"
    if aux_log.is_file() and (refgs is None or refgs.depth_prior_iters is None):
        aux = json.loads(aux_log.read_text()).get("config", {}).get("iters")
        refgs = replace(refgs or RefGSConfig(), depth_prior_iters=aux)
    return replace(base, resolution=plan["key"]["resolution"], iters_refgs=st["refgs"],
                   refgs_schedule_iters=span, refgs=refgs,
                   iters_ted_finetune=st["ted_finetune"], iters_ted_adversarial=st["ted_adversarial"],
                   prior_seconds=plan["prior_seconds"])  # fmt: skip


TEXTURE_SOURCES = {  # (folder under the run, views): the images each stage hands to the next
    "initial": ("1_inpaint/images", "train"),
    "clg": ("3_clg/images", "train"),
    "render_train": ("eval/renders", "train"),
    "render_test": ("eval/renders", "test"),
}


def texture_by_stage(run: Path, scene) -> dict:
    """Mean texture inside the masks (`metrics.mask_texture`) of the object-absent ground truth
    (test views) and of each stage's images, the latter as ratios to the former. Training views
    have no object-absent truth, so this compares views of one region, not pixels: it shows which
    stage loses the texture the HF ratio misses (NaN where the row skips a stage)."""
    from coin_cl.metrics import mask_texture
    from coin_cl.scene.io import read_image

    status = {k: v["status"] for k, v in json.loads((run / "log.json").read_text())["stages"].items()}

    def mean(views, folder: Path | None) -> float:
        if folder is not None:  # a stage this row skipped may have left a folder of another run
            stage = folder.relative_to(run).parts[0]
            if status.get(stage) not in ("ran", "skipped: up to date"):
                return float("nan")
        vals = []
        for i in views:
            m = np.asarray(scene.masks[i], bool)
            p = None if folder is None else folder / f"{Path(scene.cameras[i].name).stem}.png"
            if not m.any() or (p is not None and not p.is_file()):
                continue
            vals.append(mask_texture(scene.images[i] if p is None else read_image(p), m))
        return float(np.mean(vals)) if vals else float("nan")

    gt = mean(scene.test_idx, None)
    views = {"train": scene.train_idx, "test": scene.test_idx}
    return {"gt": gt, **{k: mean(views[v], run / d) / gt for k, (d, v) in TEXTURE_SOURCES.items()}}


def print_texture(args: argparse.Namespace, names) -> dict:
    """`texture_by_stage` of the rows' folders under --out, printed as a table; {row: figures}."""
    scene = load_scene(args.data, resolution=args.resolution)
    texture = {name: texture_by_stage(args.out / name, scene) for name in names}
    gt = next(iter(texture.values()))["gt"] if texture else float("nan")
    print(f"\nTexture in the masks (mean Sobel gradient magnitude), ratio to the object-absent truth's "
          f"({gt:.4f}, test views):\n\n| row | initial inpaints | CLG images | renders (train views) | "
          "renders (test views) |\n|---|---|---|---|---|")  # fmt: skip
    for name, t in texture.items():
        cells = [f"{t[k]:.3f}" if np.isfinite(t[k]) else "-" for k in TEXTURE_SOURCES]
        print(f"| {name} | " + " | ".join(cells) + " |")
    return texture


def reference_rows(args: argparse.Namespace, base: CoInConfig, rows: dict) -> dict:
    """The coin row and `args.refs - 1` rows with other reference views (added to `rows` too)."""
    scene = load_scene(args.data, resolution=args.resolution)
    chosen = int(json.loads((args.out / "coin" / "2_refgs" / "manifest.json").read_text())["settings"]["ref"])
    out = {"coin": {**rows["coin"], "ref": scene.cameras[chosen].name}}
    for i in other_references(scene, chosen, args.refs, args.seed):
        name = f"ref_{Path(scene.cameras[i].name).stem}"
        rows[name] = out[name] = {**run_row(name, args.data, args.out, replace(base, ref=i)),
                                  "ref": scene.cameras[i].name}  # fmt: skip
        print(name, json.dumps(rows[name], default=str), file=sys.stderr, flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--budget", type=float, default=30.0, help="training minutes per full-pipeline row")
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/out/coin (or coin_insertion)")
    ap.add_argument("--only", choices=["insertion"], help="run the synthetic insertion rows instead of these")
    ap.add_argument("--steps-from", type=Path, default=None, metavar="RUN",
                    help="the full-pipeline rows take RUN's plan.json (its resolution, step counts after "
                         "TE-D's re-plan, scene prior seconds) instead of a timing probe: the same "
                         "schedule as RUN on any load (e.g. OUT/default of a quiet run)")  # fmt: skip
    ap.add_argument("--texture-only", action="store_true",
                    help="print the texture table of the rows already under --out; run nothing")  # fmt: skip
    import coin_insertion

    coin_insertion.add_arguments(ap)
    args = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    if args.only == "insertion":
        args.out = args.out or ROOT / "benchmarks" / "out" / "coin_insertion"
        return coin_insertion.run(args)
    if args.refs is not None and args.refs < 2:
        ap.error("--refs must be at least 2 (a standard deviation needs two references)")
    args.out = args.out or ROOT / "benchmarks" / "out" / "coin"
    names = args.rows.split(",")
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        ap.error(f"unknown rows {unknown}; choose from {list(ROWS)}")
    if args.refs and "coin" not in names:
        names.append("coin")  # the default-reference row of the robustness rows
    if "coin" in names:  # the row the others start from goes first
        names = ["coin"] + [n for n in names if n != "coin"]
    if "default_baseline" in names and "default" not in names:
        names.insert(0, "default")
    if args.texture_only:
        print_texture(args, [n for n in names if (args.out / n / "log.json").is_file()])
        return 0
    base = CoInConfig(budget_minutes=args.budget, resolution=args.resolution)
    if args.steps_from is not None:
        base = steps_from(args.steps_from, base)

    rows: dict[str, dict] = {}
    for name in names:
        if name.startswith("default"):
            if "default" not in rows:
                rows.update(run_default(args.data, args.out, args.budget))
            continue
        cfg = replace(base, **ROWS[name])
        if name == "baseline" and "coin" in rows:  # the same budget: the coin row's GS steps
            cfg = replace(baseline_config(base, args.out / "coin"), **ROWS[name])
        rows[name] = run_row(name, args.data, args.out, cfg)
        print(name, json.dumps(rows[name], default=str), file=sys.stderr, flush=True)
    ref_rows = reference_rows(args, base, rows) if args.refs else {}

    from coin_cl.engine import get_runtime

    print(f"\nScene {args.data.name} at resolution {args.resolution} of images_4; "
          f"commit {git_commit()}; CPU {cpu_model()}, {os.cpu_count()} cores; OpenCL {get_runtime().name}; "
          f"budget {args.budget} min")  # fmt: skip
    print("\n| row | PSNR | SSIM | m-PSNR | m-SSIM | HF ratio | bbox GMSD | VGG-PD | m-VGG-PD | ghost "
          "| minutes this run (inpaint/refgs/clg/ted) | minutes when the stages ran (sum) |"
          "\n|---|---|---|---|---|---|---|---|---|---|---|---|")  # fmt: skip

    def f(v, d=2):
        return "n/a" if v is None else f"{v:.{d}f}"

    for name, r in rows.items():
        sm = r["stage_minutes"]
        per = "/".join(f"{sm.get(s, 0):.1f}" for s in ("1_inpaint", "2_refgs", "3_clg", "4_ted"))
        per += f" (all {r['wall_minutes']:.1f})"
        sc = r["stage_cost_minutes"]
        cost = "/".join(f"{sc.get(s, 0):.1f}" for s in ("1_inpaint", "2_refgs", "3_clg", "4_ted"))
        cost += f" ({r['cost_minutes']:.1f})"
        print(f"| {name} | {f(r['psnr'])} | {f(r['ssim'], 4)} | {f(r['m_psnr'])} | {f(r['m_ssim'], 4)} | "
              f"{f(r['hf_ratio'], 3)} | {f(r['bbox_gmsd'], 3)} | {vgg_pd_cell(r.get('vgg_pd'))} "
              f"| {vgg_pd_cell(r.get('m_vgg_pd'))} | {f(r.get('ghost'), 3)} | {per} | {cost} |")  # fmt: skip
    if any(r.get("vgg_pd") is None for r in rows.values()):
        print(f"\nVGG-PD: {vgg_pd_note() or 'absent when these rows ran'}")

    texture = print_texture(args, rows)
    if ref_rows:
        (mp, mp_sd), (hf, hf_sd) = mean_std(ref_rows, "m_psnr"), mean_std(ref_rows, "hf_ratio")
        print("\n| reference | m-PSNR | HF ratio | bbox GMSD |\n|---|---|---|---|")
        for name, r in ref_rows.items():
            cells = f"{f(r['m_psnr'])} | {f(r['hf_ratio'], 3)} | {f(r['bbox_gmsd'], 3)}"
            print(f"| {r['ref']} ({name}) | {cells} |")
        print(f"| {len(ref_rows)} references | {mp:.2f} +- {mp_sd:.2f} | {hf:.3f} +- {hf_sd:.3f} | |")

    def g(row: str, key: str):
        return rows.get(row, {}).get(key)

    result = {
        "default_mpsnr": g("default", "m_psnr"),
        "default_hf_ratio": g("default", "hf_ratio"),
        "default_gmsd": g("default", "bbox_gmsd"),
        "default_minutes": g("default", "wall_minutes"),
        "default_resolution": g("default", "resolution"),
        "default_baseline_mpsnr": g("default_baseline", "m_psnr"),
        "default_baseline_hf_ratio": g("default_baseline", "hf_ratio"),
        "default_baseline_gmsd": g("default_baseline", "bbox_gmsd"),
        "baseline_mpsnr": g("baseline", "m_psnr"),
        "baseline_hf_ratio": g("baseline", "hf_ratio"),
        "baseline_gmsd": g("baseline", "bbox_gmsd"),
        "coin_psnr": g("coin", "psnr"),
        "coin_mpsnr": g("coin", "m_psnr"),
        "coin_hf_ratio": g("coin", "hf_ratio"),
        "coin_gmsd": g("coin", "bbox_gmsd"),
        "coin_minutes": max(g("coin", "wall_minutes") or 0.0, g("coin", "cost_minutes") or 0.0) or None,
        "spinnerf_coin_mpsnr": g("default", "m_psnr"),
        "spinnerf_ghost": g("default", "ghost"),
        "spinnerf_naive_ghost": g("default_baseline", "ghost"),
        # The default takes input masks on SPIn-NeRF (16 % observed): then it is the input-mask row.
        "spinnerf_input_masks_mpsnr": g("default", "m_psnr")
        if "0_refine" not in (g("default", "status") or {})
        else g("coin", "m_psnr"),
        "seg_prior_mpsnr": g("seg_prior", "m_psnr"),
        "seg_prior_hf_ratio": g("seg_prior", "hf_ratio"),
        "bbox_mpsnr": g("bbox", "m_psnr"),
        "bbox_hf_ratio": g("bbox", "hf_ratio"),
        "texture": texture,
        "budget_minutes": args.budget,
        **(
            {
                "refs": len(ref_rows),
                "ref_mean_mpsnr": mp,
                "ref_std_mpsnr": mp_sd,
                "ref_mean_hf_ratio": hf,
                "ref_std_hf_ratio": hf_sd,
            }
            if ref_rows
            else {}
        ),
        "commit": git_commit(),
        "cpu": cpu_model(),
    }
    if "coin" in rows and "baseline" in rows:
        c, b = rows["coin"], rows["baseline"]
        result["floors"] = {
            "hf_ratio_in_0.8_1.2": bool(0.8 <= c["hf_ratio"] <= 1.2),
            "gmsd_below_baseline": bool(c["bbox_gmsd"] < b["bbox_gmsd"]),
            "mpsnr_within_0.5_of_baseline": bool(c["m_psnr"] >= b["m_psnr"] - 0.5),
            "coin_within_45_min": bool(max(c["wall_minutes"], c["cost_minutes"]) <= 45),
        }
    if "default" in rows and "default_baseline" in rows:
        d, b = rows["default"], rows["default_baseline"]
        extra = d["stage_minutes"].get("3_clg", 0.0) + d["stage_minutes"].get("eval", 0.0)
        result.setdefault("floors", {}).update({
            "default_beats_baseline_mpsnr": bool(d["m_psnr"] > b["m_psnr"]),
            "default_beats_baseline_hf_ratio": bool(abs(d["hf_ratio"] - 1) < abs(b["hf_ratio"] - 1)),
            "default_beats_baseline_gmsd": bool(d["bbox_gmsd"] < b["bbox_gmsd"]),
            "default_minutes_within_20pct": bool(
                0.8 * args.budget + extra <= d["wall_minutes"] <= 1.2 * args.budget + extra
            ),
        })  # fmt: skip
        result["default_clg_eval_minutes"] = extra
    if "seg_prior" in rows and "bbox" in rows:
        s, bb = rows["seg_prior"], rows["bbox"]
        result.setdefault("floors", {})["bbox_close_to_seg"] = bool(
            abs(bb["m_psnr"] - s["m_psnr"]) <= 0.5 and abs(bb["hf_ratio"] - s["hf_ratio"]) <= 0.1
        )
    write_result(args.out, result, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
