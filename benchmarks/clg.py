"""Benchmark: CLG (stage 3_clg, paper 4.3) on a finished pipeline run's own inputs.

Reads a run folder of `coin-cl run` / `benchmarks/coin.py` (its 0_scene/scene, 1_inpaint/images: the
initial inpaints I^_n, 2_refgs: renders, depths, alphas, reference_points.ply, and the scene prior's
cache from its 1_inpaint or 3_clg folder, copied into each row's folder so nothing retrains) and runs
`stage_clg` once per row into OUT/<row>/3_clg with the run's seed and plan, the guard on (a view whose
guided image is worse keeps its input, as in a pipeline run). Rows (`CLGConfig` variants):
    paper         sampled from noise at the working size, pasted over the mask (detail "none",
                  strength 1: the paper's CLG as written)
    detail        from noise, + the reference's band above half the working size warped through P_k
                  where supported, the initial inpaint's elsewhere (`pipeline.clg_detail`)
    input_sdedit  the sampler starts from I^_n's crop noised half way (strength 0.5), + I^_n's band
    default       CLGConfig(): strength 0.5 + the reference's band where supported, I^_n's elsewhere
    strength_03, strength_07   the default at strength 0.3 / 0.7 (not run unless named in --rows)
    no_topup      the default without the detail band's top-up (detail_gain_max 1; not run unless named)
    tol0          the default with texture_tol 0: no texture traded for consistency (not run unless named)
    run           nothing is run: the run's own 3_clg images, scored the same way (`--rows run`
                  gives a finished run's CLG figures in seconds)
Per row, over the non-reference views with a mask (a view that kept its input counts with it): the
residual to the reference of the initial inpaints (in) and of the images the row writes (out)
(`reprojection.residual_to_reference`: each view's mask pixels lifted with its Ref-GS depth where
alpha > 0.5, projected into the reference and compared with the reference's I^_k inside its mask;
CLG's guard checks the same per view, so a view worse on it keeps its input), the texture in the
masks (`metrics.mask_texture`, mean over views), the Lab colour distance to the mask's
surroundings, and how many views kept their input.
A crop grid (mask bounding boxes of a few views: initial inpaint, then each row) goes to --grid.

    COIN_DATA=... nice -n 15 python benchmarks/clg.py --run RUN [--rows paper,default] [--out DIR]

The LAST line is one JSON object: clg_residual_in, clg_residual_out, clg_texture_in, clg_texture_out,
clg_kept_input, clg_views (the default row's), and every row's figures under "rows".
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from common import cpu_model, git_commit  # noqa: E402
from crop_grid import tile_row  # noqa: E402

from coin_cl import metrics  # noqa: E402
from coin_cl.pipeline.budget import read_plan  # noqa: E402
from coin_cl.pipeline.clg import stage_clg  # noqa: E402
from coin_cl.pipeline.clg_config import CLGConfig  # noqa: E402
from coin_cl.pipeline.clg_guard import colour_distance  # noqa: E402
from coin_cl.pipeline.coin import CoInConfig  # noqa: E402
from coin_cl.pipeline.reprojection import residual_to_reference  # noqa: E402
from coin_cl.pipeline.run_inputs import RunInputs  # noqa: E402
from coin_cl.pipeline.runner import StageContext  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402
from coin_cl.scene.io import read_image, to_uint8, view_stem, write_png  # noqa: E402

ROWS = {
    "paper": CLGConfig(detail="none", strength=1.0),
    "detail": CLGConfig(detail="reference", strength=1.0),
    "input_sdedit": CLGConfig(detail="input"),
    "default": CLGConfig(),
    "strength_03": CLGConfig(strength=0.3),
    "strength_07": CLGConfig(strength=0.7),
    "no_topup": CLGConfig(detail_gain_max=1.0),
    "tol0": CLGConfig(texture_tol=0.0),
}
DEFAULT_ROW = "default"
OWN_ROW = "run"  # the run's own 3_clg, scored without running anything


def row_dir(run: Path, out: Path, row: str) -> Path:
    """The folder holding a row's 3_clg: the run itself for OWN_ROW, else out/<row>."""
    return run if row == OWN_ROW else out / row


def run_row(run: Path, out: Path, cfg: CLGConfig, scene, masks, ref: int, plan: dict) -> tuple[dict, float]:
    """stage_clg on the run's folders with `cfg` into out/3_clg; (result, seconds)."""
    dst = out / "3_clg"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    # the scene prior the run trained (or the first row, when the run's is for other settings): reused
    cache = out.parent / "prior_cache"
    for folder in (run / "1_inpaint", run / "3_clg", cache):
        for p in folder.glob("scene_prior_*.pt"):
            shutil.copy(p, dst / p.name)
    ccfg = CoInConfig(clg=replace(cfg, progress=True), seed=int(plan["key"]["seed"]))
    # The run's scene prior seconds alone (no measured prior_steps): the prior's fixed-rate steps.
    given = replace(read_plan(run / "plan.json"), prior_steps=None)
    inputs = RunInputs(out=run, scene=scene, masks=masks, ref=ref, cfg=ccfg, plan=given,
                       refgs_cfg=ccfg.refgs_settings(ref))  # fmt: skip
    ctx = StageContext("3_clg", dst, {"1_inpaint": run / "1_inpaint", "2_refgs": run / "2_refgs"}, {}, inputs)
    t0 = time.perf_counter()
    res = stage_clg(ctx)
    secs = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    for p in dst.glob("scene_prior_*.pt"):
        if not (cache / p.name).is_file():
            shutil.copy(p, cache / p.name)
    return res, secs


def score(run: Path, out: Path, scene, masks, ref: int, res: dict) -> dict:
    """The row's figures over its non-reference views with a mask (module docstring)."""
    from coin_cl.gs.targets import composite_targets

    n = len(scene)
    depths, regions = [None] * n, [None] * n
    inputs, outputs = [None] * n, [None] * n
    tex_in, tex_out, col_in, col_out = [], [], [], []
    gs = run / "2_refgs"
    for i in scene.train_idx:
        stem = view_stem(scene.cameras[i].name, i)
        m = np.asarray(masks[i], bool)
        inp = composite_targets(read_image(run / "1_inpaint" / "images" / f"{stem}.png"), scene.images[i], m)
        if i == ref:
            ref_img = inp
            continue
        png = out / "3_clg" / "images" / f"{stem}.png"
        if not m.any() or not png.is_file():
            continue
        d = np.load(gs / "depths" / f"{stem}.npy")
        a = gs / "alphas" / f"{stem}.npy"
        ok = np.isfinite(d) & ((np.load(a) > 0.5) if a.is_file() else True)
        depths[i], regions[i] = d, m & ok
        inputs[i] = to_uint8(inp).astype(np.float32) / 255  # as a PNG holds it
        outputs[i] = read_image(png)
        tex_in.append(metrics.mask_texture(inputs[i], m))
        tex_out.append(metrics.mask_texture(outputs[i], m))
        col_in.append(colour_distance(inputs[i], m))
        col_out.append(colour_distance(outputs[i], m))
    mk = np.asarray(masks[ref], bool)
    r_in = residual_to_reference(scene.cameras, depths, inputs, regions, ref, ref_img, mk)
    r_out = residual_to_reference(scene.cameras, depths, outputs, regions, ref, ref_img, mk)
    return {"residual_in": r_in, "residual_out": r_out, "texture_in": float(np.mean(tex_in)),
            "texture_out": float(np.mean(tex_out)), "colour_in": float(np.nanmean(col_in)),
            "colour_out": float(np.nanmean(col_out)), "views": len(tex_in),
            "kept_input": int(res["n_kept_input"]), "guided": int(res["n_guided"])}  # fmt: skip


def grid(
    run: Path, out: Path, rows: list[str], scene, masks, ref: int, n_views: int, cell: int
) -> np.ndarray:
    """Crop grid: per view (n_views spread over the guided ones) the mask's bounding box + 8 px of the
    initial inpaint, then each row's 3_clg image; uint8."""
    views = [i for i in scene.train_idx if i != ref and np.asarray(masks[i]).any()]
    views = [views[j] for j in np.linspace(0, len(views) - 1, min(n_views, len(views))).astype(int)]
    lines = []
    for i in views:
        stem = view_stem(scene.cameras[i].name, i)
        crop = metrics.bbox_crop(np.asarray(masks[i], bool), pad=8)
        tiles = [read_image(run / "1_inpaint" / "images" / f"{stem}.png")]
        tiles += [read_image(row_dir(run, out, r) / "3_clg" / "images" / f"{stem}.png") for r in rows]
        lines.append(tile_row([t[crop] for t in tiles], cell))
    return to_uint8(np.concatenate(lines, axis=0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="a finished pipeline run folder")
    ap.add_argument("--rows", default="paper,detail,input_sdedit,default", help=f"of {', '.join(ROWS)}")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "clg")
    ap.add_argument("--grid", type=Path, default=None, help="crop grid PNG (default OUT/grid.png)")
    ap.add_argument("--grid-views", type=int, default=6)
    ap.add_argument("--cell", type=int, default=128)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    run = args.run
    for need in ("0_scene/scene", "1_inpaint/images", "2_refgs/depths", "plan.json"):
        if not (run / need).exists():
            raise SystemExit(f"{run} is not a finished pipeline run: {need} is missing (run coin-cl run)")
    plan = json.loads((run / "plan.json").read_text())
    scene = load_scene(run / "0_scene" / "scene")
    masks = [np.asarray(m, bool) for m in scene.masks]
    from coin_cl.scene.ply import read_points_ply  # noqa: F401  (stage_clg reads P_k from 2_refgs)

    ref = int(json.loads((run / "2_refgs" / "stage.json").read_text())["reference"]["index"])
    rows = [r for r in args.rows.split(",") if r]
    bad = [r for r in rows if r not in ROWS and r != OWN_ROW]
    if bad:
        raise SystemExit(f"unknown rows {bad}: choose from {', '.join(ROWS)}, {OWN_ROW}")
    figs: dict[str, dict] = {}
    for r in rows:
        if r == OWN_ROW:
            man = run / "3_clg" / "manifest.json"
            if not man.is_file():
                raise SystemExit(f"{man} not found: the run has no finished CLG stage")
            res, secs = json.loads(man.read_text())["result"], 0.0
        else:
            res, secs = run_row(run, args.out / r, ROWS[r], scene, masks, ref, plan)
        figs[r] = score(run, row_dir(run, args.out, r), scene, masks, ref, res) | {"minutes": secs / 60}
        print(r, json.dumps(figs[r]), file=sys.stderr, flush=True)
    cam = scene.cameras[ref]
    from coin_cl.engine import get_runtime

    print(f"\nCLG on {run} ({cam.width}x{cam.height}, reference {cam.name}); commit {git_commit()}; "
          f"CPU {cpu_model()}, {os.cpu_count()} cores; OpenCL device {get_runtime().name}")  # fmt: skip
    print(
        "\n| row | residual to ref: in | out | texture: in | out | colour dist: in | out "
        "| kept input / views | min |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r, f in figs.items():
        print(f"| {r} | {f['residual_in']:.4f} | {f['residual_out']:.4f} | {f['texture_in']:.4f} | "
              f"{f['texture_out']:.4f} | {f['colour_in']:.1f} | {f['colour_out']:.1f} | "
              f"{f['kept_input']} / {f['views']} | {f['minutes']:.1f} |")  # fmt: skip
    gpath = args.grid or args.out / "grid.png"
    write_png(gpath, grid(run, args.out, rows, scene, masks, ref, args.grid_views, args.cell))
    print(f"\ncrop grid {gpath}: columns initial inpaint | {' | '.join(rows)}")
    d = figs.get(DEFAULT_ROW) or next(iter(figs.values()))
    print(json.dumps({"clg_residual_in": d["residual_in"], "clg_residual_out": d["residual_out"],
                      "clg_texture_in": d["texture_in"], "clg_texture_out": d["texture_out"],
                      "clg_kept_input": d["kept_input"], "clg_views": d["views"], "rows": figs,
                      "run": str(run), "commit": git_commit(), "cpu": cpu_model()}))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
