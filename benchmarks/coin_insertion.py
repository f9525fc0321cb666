"""`benchmarks/coin.py --only insertion`: insertion from one edited view, 3D-first refined
masks, scribble masks and the choice of reference, on synthetic rooms generated here (exact ground
truth, no weights, no dataset). It does not run the SPIn-NeRF rows of coin.py.

Rows (each a `coin_cl.inpaint` run folder under --out; rows on one scene start from another row's
stage folders with `share_stages`, and the runner keeps exactly those whose settings match):
    insert        the room *without* the red box, the reference view edited by pasting the box's true
                  appearance (`paste_object`), the full pipeline with `edited_ref`
    insert_naive  the naive alternative: `InsertConfig(propagate=False)`, plain Scaffold-GS on the
                  edited reference beside the unedited views, as many GS steps as insert's Ref-GS + TE-D
    insert_one_photo  what a user has: the same room and edited reference but no mask in any view;
                  the box is stood on the table under it and every view's region derived
                  (`coin_cl.pipeline.insert_geometry`, `InsertConfig.regions = "derive"`; the
                  default profile, a solid of revolution)
    insert_one_photo_extrude  the same with the prism profile (`InsertConfig.profile = "extrude"`)
    input_360     removal on a 360-degree capture with the input (seg) masks
    refined_360   the same with 3D-first refined masks (`inpaint_region="refined"`, stage 0_refine)
    seg           removal on the room (a 90-degree arc, forward-facing) with seg masks; also the
                  default-reference run of the reference robustness
    scribble      the same with scribble masks (seg plus seeded random strokes); bbox on request
    ref_<view>    the seg run with another reference view (N-1 random training views, seeded)
Insertion is scored on the views other than the reference against the room *with* the box: m-PSNR
in the box's true footprint (the held-out test views, and the other training views), the median
absolute depth error there (scene units, about metres; the render's expected depth against the
ray-cast depth of the box, on pixels whose centre sees the box), and how far the footprint's redness
goes from the empty room's toward the box's (1 = all of the box's colour arrives; the box is the
only saturated red in the room). Removal rows are scored by the pipeline's evaluation on the
object-absent test views (m-PSNR, HF ratio inside the object's true mask).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from common import cpu_model, git_commit, mean_std, other_references, write_result

from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig, CoInResult, inpaint
from coin_cl.pipeline.insert_config import InsertConfig
from coin_cl.pipeline.refine_masks import RefineConfig
from coin_cl.pipeline.runner import share_stages
from coin_cl.scene import load_scene
from coin_cl.scene.io import view_stem
from coin_cl.scene.synthetic import (
    SyntheticScene,
    make_synthetic,
    paste_object,
    truly_unseen,
    write_synthetic,
)

log = logging.getLogger("bench.coin_insertion")

# A user's mask covers the object with a margin; the generator's are exact silhouettes, whose edge
# pixels would fall out of the visual hull (as tests/test_pipeline_insert.py does).
INSERT_DILATE = 1
# A pixel is "red" (the inserted box's colour) above this redness; the room has almost none.
RED = 0.25


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The flags of this path, as a group of coin.py's parser."""
    g = ap.add_argument_group("--only insertion (synthetic rooms)")
    g.add_argument("--size", default="96x72", help="WxH of the synthetic views")
    g.add_argument("--views", type=int, default=16, help="views per scene (one in four a test view)")
    g.add_argument("--iters", type=int, default=300, help="Ref-GS steps")
    g.add_argument("--ted-iters", type=int, default=80, help="TE-D steps per phase (fine-tune, adversarial)")
    g.add_argument("--refine-iters", type=int, default=300, help="steps of the object-present fit (0_refine)")
    g.add_argument("--prior-seconds", type=float, default=120.0,
                   help="scene prior training seconds (120 = the pipeline's floor)")  # fmt: skip
    g.add_argument("--clg-steps", type=int, default=10, help="CLG sampling steps (removal)")
    g.add_argument(
        "--refs", type=int, default=None, help="reference views, robustness rows (>= 2; default 3)"
    )
    g.add_argument("--mask-kinds", default="seg,scribble", help="mask rows on the room: seg,scribble[,bbox]")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--insertion-rows-only", action="store_true",
                   help="only the insertion rows (insert, insert_naive, insert_one_photo[_extrude]; "
                        "no removal rows)")  # fmt: skip


def _scene(root: Path, **kw) -> tuple[SyntheticScene, object]:
    """(generated scene in memory, the folder loaded): written once; rewritten when its settings
    change (the run folders of another scene then refuse it: pick another --out)."""
    syn = make_synthetic(**kw)
    info = root / "scene_info.json"
    if info.is_file() and any(json.loads(info.read_text()).get(k) != v for k, v in syn.params.items()):
        shutil.rmtree(root)
    if not info.is_file():
        write_synthetic(root, syn)
    return syn, load_scene(root)


def _syn_index(syn: SyntheticScene, name: str) -> int:
    return next(j for j, c in enumerate(syn.cameras) if c.name == name)


def redness(img: np.ndarray) -> np.ndarray:
    """R minus the larger of G and B, (H, W): the inserted box is the room's only saturated red."""
    return img[..., 0] - img[..., 1:].max(-1)


def _render(res: CoInResult, cam) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3), expected depth (H, W)) of the final model in view `cam`."""
    import torch

    with torch.no_grad():
        r = res.model.render(cam, 10**9, return_depth=True)
    return r.image.clamp(0, 1).numpy(), r.depth.numpy()


def score_insertion(res: CoInResult, scene, syn: SyntheticScene, ref_name: str) -> dict:
    """Per view other than the reference (module doc), then means / medians over them."""
    from coin_cl.metrics import masked_psnr
    from coin_cl.scene.masks import dilate_mask

    test, train = set(scene.test_idx), set(scene.train_idx)
    per: dict[str, dict] = {}
    for i in sorted(test | train):
        cam = scene.cameras[i]
        if cam.name == ref_name:
            continue
        j = _syn_index(syn, cam.name)
        foot = syn.masks[j]
        gt, empty = syn.present[j], syn.absent[j]
        img, depth = _render(res, cam)
        # depth where the pixel centre sees the box (its footprint counts any subsample's coverage)
        onbox = foot & (syn.depth_present[j] < syn.depth_absent[j])
        dgt = syn.depth_present[j][onbox]
        err = np.abs(depth[onbox] - dgt)
        r_gt, r_empty = redness(gt)[foot].mean(), redness(empty)[foot].mean()
        far = ~dilate_mask(foot, kernel=3, iterations=4)
        per[cam.name] = {
            "split": "test" if i in test else "train",
            "m_psnr": masked_psnr(img, gt, foot),
            "m_psnr_empty": masked_psnr(empty, gt, foot),  # what showing no box at all scores
            "depth_err": float(np.median(err)) if err.size else math.nan,
            "depth_rel": float(np.median(err / dgt)) if err.size else math.nan,
            "depth_err_empty": float(np.median(np.abs(syn.depth_absent[j][onbox] - dgt)))
            if err.size else math.nan,
            "colour_reach": float((redness(img)[foot].mean() - r_empty) / (r_gt - r_empty)),
            "leak": float(np.mean(redness(img)[far] > RED) - np.mean(redness(empty)[far] > RED)),
        }  # fmt: skip

    def mean(key: str, split: str | None = None) -> float:
        v = [p[key] for p in per.values() if split is None or p["split"] == split]
        v = [x for x in v if np.isfinite(x)]
        return float(np.mean(v)) if v else math.nan

    def median(key: str) -> float:
        v = [p[key] for p in per.values() if np.isfinite(p[key])]
        return float(np.median(v)) if v else math.nan

    return {
        "m_psnr": mean("m_psnr", "test"),
        "m_psnr_train": mean("m_psnr", "train"),
        "m_psnr_empty": mean("m_psnr_empty", "test"),
        "depth_err": median("depth_err"),
        "depth_rel": median("depth_rel"),
        "depth_err_empty": median("depth_err_empty"),
        "colour_reach": median("colour_reach"),
        "leak_max": max(p["leak"] for p in per.values()),
        "pipeline_m_psnr": (res.metrics or {}).get("m_psnr"),
        "per_view": per,
    }


def _run(scene, out: Path, cfg: CoInConfig, share_from: Path | None = None, stages=("0_scene",),
         **kw) -> tuple[CoInResult, float]:  # fmt: skip
    """One pipeline run (`share_from`: start from that run's `stages` folders). (result, minutes)."""
    if share_from is not None and share_from.is_dir():
        share_stages(share_from, out, stages)
    t = time.perf_counter()
    res = inpaint(scene, out, config=cfg, **kw)
    return res, (time.perf_counter() - t) / 60


def _ran(res: CoInResult) -> str:
    """Which stages this row ran itself (the rest were shared or skipped)."""
    return ",".join(k for k, r in res.stages.items() if r["status"] == "ran") or "none"


def _progress(name: str, row: dict) -> None:
    brief = {k: v for k, v in row.items() if k != "per_view"}
    print(f"[coin --only insertion] {name}: {json.dumps(brief, default=str)}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from coin_cl.engine import get_runtime

    w, h = (int(v) for v in args.size.lower().split("x"))
    args.refs = 3 if args.refs is None else args.refs
    if args.refs < 2:
        raise SystemExit("--refs must be at least 2 (a standard deviation needs two references)")
    kinds = args.mask_kinds.split(",")
    if "seg" not in kinds or not set(kinds) <= {"seg", "bbox", "scribble"}:
        raise SystemExit(f"--mask-kinds must include seg and only name seg, bbox, scribble; got {kinds}")
    out: Path = args.out
    t_all = time.perf_counter()
    # One configuration for every row: rows differ only in what their row changes, so stages shared
    # between them have equal settings and the manifests let the runner skip them.
    base = CoInConfig(
        iters_refgs=args.iters, iters_ted_finetune=args.ted_iters, iters_ted_adversarial=args.ted_iters,
        prior_seconds=args.prior_seconds, clg=CLGConfig(steps=args.clg_steps), refgs=RefGSConfig(),
        refine=RefineConfig(iters=args.refine_iters), seed=args.seed,
    )  # fmt: skip
    gen = {"n_views": args.views, "width": w, "height": h, "seed": args.seed, "n_points": 4000}
    rows: dict[str, dict] = {}

    # -- insertion from an edited reference ------------------------------------------------------
    syn_i, sc_i = _scene(out / "scenes" / "insertion", task="insertion", coverage=180, **gen)
    from coin_cl.pipeline.reference import choose_reference

    train = list(sc_i.train_idx)
    k = choose_reference(sc_i.masks, sc_i.cameras, train_idx=train)  # the view a user would edit
    edited = paste_object(sc_i.images[k], sc_i.extras["object_present"][k], sc_i.masks[k])
    icfg = replace(base, mask_dilate=INSERT_DILATE)
    res, minutes = _run(sc_i, out / "insert", icfg, edited_ref=edited)
    ref_name = sc_i.cameras[k].name
    if res.stages["1_inpaint"]["result"]["reference"] != ref_name:
        raise RuntimeError(f"the edit of {ref_name} was matched to {res.stages['1_inpaint']['result']}")
    rows["insert"] = {**score_insertion(res, sc_i, syn_i, ref_name), "minutes": minutes, "ran": _ran(res)}
    _progress("insert", rows["insert"])
    ncfg = replace(icfg, skip=("refgs", "clg", "ted"), insert=InsertConfig(propagate=False),
                   iters_refgs=args.iters + 2 * args.ted_iters)  # same GS steps in all  # fmt: skip
    res_n, minutes = _run(sc_i, out / "insert_naive", ncfg, out / "insert", edited_ref=edited)
    rows["insert_naive"] = {**score_insertion(res_n, sc_i, syn_i, ref_name), "minutes": minutes,
                            "ran": _ran(res_n)}  # fmt: skip
    _progress("insert_naive", rows["insert_naive"])
    # no mask anywhere: not sharing insert's 0_scene, whose saved masks are the hull path's
    none = [np.zeros_like(m) for m in sc_i.masks]
    one = replace(icfg, insert=InsertConfig(regions="derive"))
    res_1, minutes = _run(sc_i, out / "insert_one_photo", one, edited_ref=edited, masks=none)
    rows["insert_one_photo"] = {**score_insertion(res_1, sc_i, syn_i, ref_name), "minutes": minutes,
                                "ran": _ran(res_1), **_regions(res_1, sc_i, syn_i)}  # fmt: skip
    _progress("insert_one_photo", rows["insert_one_photo"])
    prism = replace(icfg, insert=InsertConfig(regions="derive", profile="extrude"))
    res_e, minutes = _run(sc_i, out / "insert_one_photo_extrude", prism, edited_ref=edited, masks=none)
    rows["insert_one_photo_extrude"] = {**score_insertion(res_e, sc_i, syn_i, ref_name), "minutes": minutes,
                                        "ran": _ran(res_e), **_regions(res_e, sc_i, syn_i)}  # fmt: skip
    _progress("insert_one_photo_extrude", rows["insert_one_photo_extrude"])
    _rows_grid(out, sc_i, syn_i, {"insert": res, "insert_naive": res_n, "insert_one_photo": res_1,
                                  "insert_one_photo_extrude": res_e})  # fmt: skip
    if args.insertion_rows_only:
        _insertion_table(rows, ref_name)
        keys = ("m_psnr", "m_psnr_train", "depth_err", "depth_rel", "colour_reach", "leak_max", "minutes")
        summary = {f"{n}_{k}": rows[n].get(k) for n in rows for k in keys}
        run_info = {"size": [w, h], "views": args.views, "iters": args.iters, "ted_iters": args.ted_iters,
                    "commit": git_commit(), "cpu": cpu_model()}  # fmt: skip
        write_result(out, {**summary, **run_info}, rows)
        return 0

    # -- refined vs input masks on a 360-degree capture (removal) ---------------------------------
    syn_r, sc_r = _scene(out / "scenes" / "room360", task="removal", coverage=360, **gen)
    res_in, minutes = _run(sc_r, out / "input_360", base)
    rows["input_360"] = {**_removal(res_in), "minutes": minutes, "ran": _ran(res_in)}
    _progress("input_360", rows["input_360"])
    refined = replace(base, inpaint_region="refined")
    res_rf, minutes = _run(sc_r, out / "refined_360", refined, out / "input_360")
    rows["refined_360"] = {**_removal(res_rf), **_refined_masks(res_rf, sc_r, syn_r), "minutes": minutes,
                           "ran": _ran(res_rf)}  # fmt: skip
    _progress("refined_360", rows["refined_360"])

    # -- mask kinds and reference robustness on the forward-facing room (removal) -----------------
    syn_f, sc_f = _scene(out / "scenes" / "room90", task="removal", coverage=90, **gen)
    res_seg, minutes = _run(sc_f, out / "seg", base)
    seg_ref = int(json.loads((out / "seg" / "2_refgs" / "manifest.json").read_text())["settings"]["ref"])
    rows["seg"] = {**_removal(res_seg), "ref": sc_f.cameras[seg_ref].name, "minutes": minutes,
                   "ran": _ran(res_seg)}  # fmt: skip
    _progress("seg", rows["seg"])
    for kind in [x for x in kinds if x != "seg"]:
        r, minutes = _run(sc_f, out / kind, replace(base, mask=kind))
        rows[kind] = {**_removal(r), "minutes": minutes, "ran": _ran(r)}
        _progress(kind, rows[kind])
    others = other_references(sc_f, seg_ref, args.refs, args.seed)
    ref_rows = {"seg": rows["seg"]}
    for i in others:
        name = f"ref_{view_stem(sc_f.cameras[i].name, i)}"
        # stages 0 and 1 do not depend on the reference: they come from the seg row
        r, minutes = _run(sc_f, out / name, replace(base, ref=i), out / "seg", ("0_scene", "1_inpaint"))
        rows[name] = ref_rows[name] = {**_removal(r), "ref": sc_f.cameras[i].name, "minutes": minutes,
                                       "ran": _ran(r)}  # fmt: skip
        _progress(name, rows[name])

    # -- report ----------------------------------------------------------------------------------
    dev = get_runtime().name
    total = (time.perf_counter() - t_all) / 60
    _grid(out, sc_i, syn_i, res, res_n, ref_name, sc_r, syn_r, res_rf)
    print(f"\nSynthetic rooms at {w}x{h}, {args.views} views (one in four a test view with ground truth); "
          f"commit {git_commit()}; CPU {cpu_model()}, {os.cpu_count()} cores; "
          f"OpenCL {dev}; Ref-GS {args.iters} steps, TE-D {args.ted_iters}+{args.ted_iters}, CLG "
          f"{args.clg_steps} steps (removal), scene prior {args.prior_seconds:.0f} s, 0_refine fit "
          f"{args.refine_iters} steps; {total:.1f} min in all")  # fmt: skip

    def f(v, d=2):
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"

    _insertion_table(rows, ref_name)

    print("\nRemoval, refined vs input masks (360-degree capture)")
    print("\n| row | m-PSNR | HF ratio | PSNR | refined / input mask area | truly-unseen recall | "
          "refined px truly unseen | minutes | stages run |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ("input_360", "refined_360"):
        r = rows[name]
        print(f"| {name} | {f(r['m_psnr'])} | {f(r['hf_ratio'], 3)} | {f(r['psnr'])} | "
              f"{f(r.get('refined_mask_ratio', 1.0), 3)} | {f(r.get('unseen_recall'), 3)} | "
              f"{f(r.get('unseen_precision'), 3)} | {r['minutes']:.1f} | {r['ran']} |")  # fmt: skip

    print("\nRemoval, mask kinds and reference views (forward-facing room, 90-degree arc)")
    print("\n| row | mask | reference | m-PSNR | HF ratio | PSNR | minutes | stages run |")
    print("|---|---|---|---|---|---|---|---|")
    for name in ["seg"] + [x for x in kinds if x != "seg"] + [n for n in ref_rows if n != "seg"]:
        r = rows[name]
        kind = name if name in kinds else "seg"
        print(f"| {name} | {kind} | {r.get('ref', '(rule)')} | {f(r['m_psnr'])} | {f(r['hf_ratio'], 3)} | "
              f"{f(r['psnr'])} | {r['minutes']:.1f} | {r['ran']} |")  # fmt: skip
    (mp, mp_sd), (hf, hf_sd) = mean_std(ref_rows, "m_psnr"), mean_std(ref_rows, "hf_ratio")
    print(f"| {len(ref_rows)} references | seg | | {mp:.2f} +- {mp_sd:.2f} | {hf:.3f} +- {hf_sd:.3f} | | | |")

    def g(row: str, key: str):
        return rows.get(row, {}).get(key)

    result = {
        "insert_mpsnr": g("insert", "m_psnr"),
        "insert_naive_mpsnr": g("insert_naive", "m_psnr"),
        "insert_mpsnr_train": g("insert", "m_psnr_train"),
        "insert_naive_mpsnr_train": g("insert_naive", "m_psnr_train"),
        "insert_empty_mpsnr": g("insert", "m_psnr_empty"),
        "insert_depth_err": g("insert", "depth_err"),
        "insert_naive_depth_err": g("insert_naive", "depth_err"),
        "insert_empty_depth_err": g("insert", "depth_err_empty"),
        "insert_colour_reach": g("insert", "colour_reach"),
        "insert_naive_colour_reach": g("insert_naive", "colour_reach"),
        "insert_leak_max": g("insert", "leak_max"),
        "insert_one_photo_mpsnr": g("insert_one_photo", "m_psnr"),
        "insert_one_photo_depth_rel": g("insert_one_photo", "depth_rel"),
        "insert_one_photo_colour_reach": g("insert_one_photo", "colour_reach"),
        "insert_one_photo_leak_max": g("insert_one_photo", "leak_max"),
        "refined_mask_ratio": g("refined_360", "refined_mask_ratio"),
        "refined_unseen_recall": g("refined_360", "unseen_recall"),
        "refined_mpsnr": g("refined_360", "m_psnr"),
        "refined_hf_ratio": g("refined_360", "hf_ratio"),
        "input_360_mpsnr": g("input_360", "m_psnr"),
        "input_360_hf_ratio": g("input_360", "hf_ratio"),
        "seg_mpsnr": g("seg", "m_psnr"),
        "scribble_mpsnr": g("scribble", "m_psnr"),
        "scribble_hf_ratio": g("scribble", "hf_ratio"),
        "bbox_mpsnr": g("bbox", "m_psnr"),
        "refs": len(ref_rows),
        "ref_mean_mpsnr": mp,
        "ref_std_mpsnr": mp_sd,
        "ref_mean_hf_ratio": hf,
        "ref_std_hf_ratio": hf_sd,
        "size": [w, h],
        "views": args.views,
        "minutes": total,
        "commit": git_commit(),
        "cpu": cpu_model(),
        "device": dev,
    }
    write_result(out, result, rows)
    return 0


def _f(v, d=2) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"


def _insertion_table(rows: dict, ref_name: str) -> None:
    f = _f
    print(
        f"\nInsertion from one edited view (reference {ref_name}; other views against the room with the box)"
    )
    print("\n| row | m-PSNR test | m-PSNR other train | depth err (median, m) | rel. | colour reach | "
          "leak (max) | minutes | stages run |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ("insert", "insert_naive", "insert_one_photo", "insert_one_photo_extrude"):
        r = rows[name]
        print(f"| {name} | {f(r['m_psnr'])} | {f(r['m_psnr_train'])} | {f(r['depth_err'], 3)} | "
              f"{f(r['depth_rel'], 3)} | {f(r['colour_reach'], 3)} | {f(r['leak_max'], 4)} | "
              f"{r['minutes']:.1f} | {r['ran']} |")  # fmt: skip
    ri = rows["insert"]
    empty = f"{f(ri['m_psnr_empty'])} | | {f(ri['depth_err_empty'], 3)} | | 0 | | | |"
    print(f"| (no box: the empty room) | {empty}")
    for name in ("insert_one_photo", "insert_one_photo_extrude"):
        r1 = rows[name]
        print(f"\n{name}'s derived regions against the box's true footprint: recall min "
              f"{f(r1['region_recall_min'], 3)}, area / true area max "
              f"{f(r1['region_area_max'], 2)}")  # fmt: skip


def _regions(res: CoInResult, scene, syn: SyntheticScene) -> dict:
    """The derived regions (0_scene's saved masks) against the box's true footprint, over the
    views other than the reference: the lowest recall and the largest area ratio."""
    from coin_cl.scene import load_scene as _load

    saved = _load(res.out / "0_scene" / "scene")
    ref = res.stages["1_inpaint"]["result"]["reference"]
    rec, area = [], []
    for i, cam in enumerate(scene.cameras):
        if cam.name == ref:
            continue
        true, got = syn.masks[_syn_index(syn, cam.name)], saved.masks[i]
        rec.append((got & true).sum() / true.sum())
        area.append(got.sum() / true.sum())
    return {"region_recall_min": float(min(rec)), "region_area_max": float(max(area))}


def _removal(res: CoInResult) -> dict:
    m = res.metrics or {}
    return {k: m.get(k) for k in ("m_psnr", "hf_ratio", "psnr", "bbox_gmsd")}


def _refined_masks(res: CoInResult, scene, syn: SyntheticScene) -> dict:
    """refined / input mask area (mean over training views with a mask), and against the
    generator's visibility (`truly_unseen`): the share of the truly unseen pixels the refined
    masks cover (recall) and the share of refined pixels that are truly unseen (precision)."""
    from coin_cl.scene.masks import read_mask

    folder = res.out / "0_refine" / "masks"
    train = [i for i in scene.train_idx if scene.masks[i].any()]
    js = [_syn_index(syn, scene.cameras[i].name) for i in train]
    all_js = [_syn_index(syn, scene.cameras[i].name) for i in scene.train_idx]
    unseen_by = dict(zip(all_js, truly_unseen(syn, all_js), strict=True))  # seen by no other training view
    ratio, recall, precision = [], [], []
    for i, j in zip(train, js, strict=True):
        m = scene.masks[i]
        r = read_mask(folder / f"{view_stem(scene.cameras[i].name, i)}.png", m.shape)
        u = unseen_by[j]
        ratio.append(r.sum() / m.sum())
        if u.any():
            recall.append((r & u).sum() / u.sum())
        if r.any():
            precision.append((r & u).sum() / r.sum())
    return {
        "refined_mask_ratio": float(np.mean(ratio)),
        "unseen_recall": float(np.mean(recall)) if recall else math.nan,
        "unseen_precision": float(np.mean(precision)) if precision else math.nan,
        "unseen_over_input": float(np.mean([unseen_by[j].sum() / syn.masks[j].sum() for j in js])),
    }


def _rows_grid(out: Path, sc_i, syn_i, results: dict) -> None:
    """out/insertion_rows.jpg: one line per insertion test view, the box's true footprint (its
    bounding box grown by half its size) of: the capture (no box) | the truth | each row's render
    in `results` ({row: CoInResult}, that order). Nearest-neighbour 3x, for the docs."""
    import cv2

    from coin_cl import metrics
    from coin_cl.scene.io import to_uint8

    lines = []
    for i in sc_i.test_idx:
        j = _syn_index(syn_i, sc_i.cameras[i].name)
        foot = np.asarray(syn_i.masks[j], bool)
        if not foot.any():
            continue
        ys, xs = np.nonzero(foot)
        crop = metrics.bbox_crop(foot, pad=max(4, int(0.5 * max(np.ptp(ys), np.ptp(xs)))))
        renders = [_render(r, sc_i.cameras[i])[0] for r in results.values()]
        tiles = [syn_i.absent[j], syn_i.present[j], *renders]
        line = np.concatenate([np.pad(np.asarray(t, np.float32)[crop], ((1, 1), (1, 1), (0, 0)),
                                      constant_values=1.0) for t in tiles], 1)  # fmt: skip
        lines.append(line)
    if not lines:
        return
    w = max(x.shape[1] for x in lines)
    img = np.concatenate([np.pad(x, ((0, 0), (0, w - x.shape[1]), (0, 0)), constant_values=1.0)
                          for x in lines])  # fmt: skip
    img = cv2.resize(to_uint8(img), None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(out / "insertion_rows.jpg"), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"crops: {out / 'insertion_rows.jpg'} (capture | truth | " + " | ".join(results) + ")")


def _grid(out: Path, sc_i, syn_i, res, res_n, ref_name: str, sc_r, syn_r, res_rf) -> None:
    """out/insertion_grid.jpg: top, the first insertion test view: captured (no box) | ground truth |
    CoIn | naive; bottom, the first 360 training view: capture | input mask | refined mask | truly
    unseen. Nearest-neighbour 2x, for the docs."""
    import cv2

    from coin_cl.scene.io import to_uint8
    from coin_cl.scene.masks import read_mask

    i = sc_i.test_idx[0]
    j = _syn_index(syn_i, sc_i.cameras[i].name)
    cam = sc_i.cameras[i]
    top = [syn_i.absent[j], syn_i.present[j], _render(res, cam)[0], _render(res_n, cam)[0]]
    n = sc_r.train_idx[0]
    stem = view_stem(sc_r.cameras[n].name, n)
    refined = read_mask(res_rf.out / "0_refine" / "masks" / f"{stem}.png", sc_r.masks[n].shape)
    train_j = [_syn_index(syn_r, sc_r.cameras[t].name) for t in sc_r.train_idx]
    unseen = truly_unseen(syn_r, train_j)[0]
    bottom = [sc_r.images[n]] + [np.repeat(m[..., None].astype(np.float32), 3, 2) for m in
                                 (sc_r.masks[n], refined, unseen)]  # fmt: skip
    gap = np.ones((top[0].shape[0], 2, 3), np.float32)

    def row(tiles: list[np.ndarray]) -> np.ndarray:
        parts = []
        for t in tiles:
            parts += [np.asarray(t, np.float32), gap]
        return np.concatenate(parts[:-1], 1)

    a, b = row(top), row(bottom)
    img = np.concatenate([a, np.ones((2, a.shape[1], 3), np.float32), b], 0)
    img = cv2.resize(to_uint8(img), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(out / "insertion_grid.jpg"), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
