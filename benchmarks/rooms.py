"""Removal geometry on the synthetic rooms: CoIn's default (inpaint region "auto": the
observed / unseen split of stage 0_refine), CoIn with the input masks, the naive baseline (plain
Scaffold-GS on CoIn's stage-1 inpaints) and masked reconstruction (3DGS on the captured views with
the object's pixels left out of the loss), both at CoIn's budget (as many steps as CoIn's Ref-GS and
TE-D together, `coin_cl.demo.baseline_steps`), on the demo room (90-degree arc, `coin-cl demo`'s
scene) and a 360-degree room.

Columns: PSNR, m-PSNR, m-PSNR on the test masks' observed / unseen parts (against the ray-cast
visibility from the training views, `coin_cl.scene.synthetic`), HF ratio, bbox GMSD, the ghost
figure (share of mask pixels rendered more than 10 % in front of the exact depth,
`coin_cl.metrics.ghost_fraction`), the split's observed share and its precision / recall of the
exactly unseen core (training views), minutes.

    nice -n 15 python benchmarks/rooms.py --out /tmp/rooms [--scenes room room360] [--iters 591 411 499]

The default steps are the plan `coin-cl demo` makes at budget 3 on a quiet machine (Ref-GS 591,
TE-D 411 + 499, scene prior 120 s), given explicitly so that a loaded machine runs the same
schedule (its timing probe would plan fewer steps).

`--mask-dilate N` sets `CoInConfig.mask_dilate` of the CoIn rows (the synthetic masks are exact).
`--rows ... coin_view_check` adds a row with stage 0_refine's view check
(`RefineConfig.view_check`); `coin_no_bg_depth` a row without the background depth term
(`RefGSConfig.bg_depth=False`, Ref-GS and TE-D; stages 0-1 shared with the coin row). `--seed`
sets every row's training seed (`CoInConfig.seed`, masked reconstruction's `TrainConfig.seed`; the
scene stays the same); `--refine-vote` / `--refine-grow` set stage 0_refine's removal vote and
growth (`RefineConfig.min_fraction`, `grow_px`; docs/RESULTS.md "Why the split inpaints what other
views saw"). The last line is JSON (room_*, room360_*).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from common import cpu_model, git_commit, vgg_pd_cell, vgg_pd_note, write_result

from coin_cl.demo import baseline_config
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.coin import CoInConfig, inpaint
from coin_cl.pipeline.refine_masks import RefineConfig
from coin_cl.pipeline.runner import share_stages

SCENES = {"room": 90, "room360": 360}
ROWS = ("coin", "naive", "masked_recon", "coin_input", "coin_view_check", "coin_no_bg_depth")
# stage 0_refine's precise split (off by default: end to end it scored lower; refine_masks' doc)
VIEW_CHECK = RefineConfig(view_check=0.05, see_through=0.0, grow_px=0)


def observed_from(syn, n: int, sources: list[int], tol: float = 0.02) -> np.ndarray:
    """(H, W) bool: the pixels of view n's mask whose object-free surface point some view of
    `sources` sees outside its own mask (the complement of `truly_unseen`, for any view n)."""
    from coin_cl.scene.synthetic import truly_unseen

    return syn.masks[n] & ~truly_unseen(syn, [n, *[s for s in sources if s != n]])[0]


def split_scores(syn, run: Path) -> dict:
    """The split of `run`'s stage 0_refine against the ray-cast truth on the training views
    (`split_counts`); {} where the run has no split."""
    from coin_cl.scene.masks import read_mask

    train = [j for j, t in enumerate(syn.is_test) if not t]
    paths = {n: run / "0_refine" / "unseen" / (Path(syn.cameras[n].name).stem + ".png") for n in train}
    if not all(p.is_file() for p in paths.values()):
        return {}
    return split_counts(syn, {n: read_mask(p, syn.masks[n].shape) for n, p in paths.items()})


def split_counts(syn, unseen_found: dict[int, np.ndarray], truth: list[np.ndarray] | None = None) -> dict:
    """A split ({training view: (H, W) bool unseen core found}) against the ray-cast truth
    (`truly_unseen` of those views, or `truth` in their order when given): observed share (found),
    exact observed share, precision / recall of the unseen core, and the share of exactly observed
    pixels it marks unseen."""
    from coin_cl.scene.synthetic import truly_unseen

    views = list(unseen_found)
    truth = truly_unseen(syn, views) if truth is None else truth
    tp = marked = unseen = obs = obs_marked = area = 0
    for n, u in zip(views, truth, strict=True):
        r, m = unseen_found[n], syn.masks[n]
        tp, marked, unseen = tp + (r & u).sum(), marked + r.sum(), unseen + u.sum()
        obs, obs_marked, area = obs + (m & ~u).sum(), obs_marked + (m & ~u & r).sum(), area + m.sum()
    return {
        "observed_share": float(1 - marked / area),
        "exact_observed_share": float(obs / area),
        "precision": float(tp / max(1, marked)),
        "recall": float(tp / max(1, unseen)),
        "observed_marked_unseen": float(obs_marked / max(1, obs)),
    }


def part_psnr(syn, pred_dir: Path) -> dict:
    """m-PSNR of the test renders in `pred_dir` on the observed and the unseen part of each test
    mask (exact visibility from the training views); means over the test views."""
    from coin_cl.metrics import masked_psnr
    from coin_cl.scene.io import read_image

    train = [j for j, t in enumerate(syn.is_test) if not t]
    obs, uns = [], []
    for n in [j for j, t in enumerate(syn.is_test) if t]:
        o = observed_from(syn, n, train)
        pred = read_image(pred_dir / syn.cameras[n].name)
        obs.append(masked_psnr(pred, syn.absent[n], o))
        uns.append(masked_psnr(pred, syn.absent[n], syn.masks[n] & ~o))
    return {"m_psnr_observed": float(np.nanmean(obs)), "m_psnr_unseen": float(np.nanmean(uns))}


def coin_row(syn, scene_dir: Path, out: Path, cfg: CoInConfig) -> dict:
    t = time.perf_counter()
    res = inpaint(scene_dir, out, config=cfg)
    m = res.metrics or {}
    row = {k: m.get(k) for k in ("psnr", "m_psnr", "hf_ratio", "bbox_gmsd", "m_vgg_pd", "ghost")}
    region = "refined" if (out / "0_refine").is_dir() else "input"
    return {
        **row,
        **part_psnr(syn, out / "eval" / "renders"),
        **split_scores(syn, out),
        "region": region,
        "minutes": (time.perf_counter() - t) / 60,
    }


def masked_recon_row(syn, scene_dir: Path, out: Path, steps: int, seed: int = 0) -> dict:
    """3DGS, `steps` steps, object pixels out of the loss (`coin_cl.demo.room_baseline`), plus its
    ghost figure from the test views' rendered depth."""
    import torch

    from coin_cl.demo import room_baseline
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.metrics import ghost_fraction
    from coin_cl.pipeline.stages import load_model

    t = time.perf_counter()
    row = room_baseline(out, scene_dir, steps, seed=seed)
    model = load_model(out / "train", CKPT_NAME, model_from_state)
    ghost = []
    for n in [j for j, t_ in enumerate(syn.is_test) if t_]:
        with torch.no_grad():
            r = model.render(syn.cameras[n], 10**9, return_depth=True)
        d = np.where(r.alpha.numpy() > 0.5, r.depth.numpy(), np.nan)
        ghost.append(ghost_fraction(d, syn.depth_absent[n], syn.masks[n]))
    keep = ("psnr", "m_psnr", "hf_ratio", "bbox_gmsd", "m_vgg_pd")
    return {
        **{k: row.get(k) for k in keep},
        "ghost": float(np.nanmean(ghost)),
        **part_psnr(syn, out / "pred"),
        "region": "-",
        "minutes": (time.perf_counter() - t) / 60,
    }


def run_scene(name: str, out: Path, args) -> dict:
    from coin_cl.scene.synthetic import make_synthetic, write_synthetic

    syn = make_synthetic(
        coverage=SCENES[name], n_views=args.views, width=args.size[0], height=args.size[1], seed=0
    )
    scene_dir = out / "scene"
    if not (scene_dir / "views.txt").is_file():
        write_synthetic(scene_dir, syn)
    cfg = CoInConfig(budget_minutes=args.budget, prior_seconds=args.prior_seconds, seed=args.seed,
                     mask_dilate=args.mask_dilate, observed=args.observed)  # fmt: skip
    refine = {
        k: v for k, v in (("min_fraction", args.refine_vote), ("grow_px", args.refine_grow)) if v is not None
    }
    cfg = replace(cfg, refine=replace(cfg.refine, **refine))  # the coin row's observed / unseen split
    if args.iters:  # explicit steps: the same schedule on a loaded machine as on a quiet one
        cfg = replace(cfg, iters_refgs=args.iters[0], iters_ted_finetune=args.iters[1],
                      iters_ted_adversarial=args.iters[2])  # fmt: skip
    rows = {}
    rows["coin"] = coin_row(syn, scene_dir, out / "coin", cfg)
    print(name, "coin", json.dumps(rows["coin"]), file=sys.stderr, flush=True)
    naive = baseline_config(cfg, out / "coin")  # CoIn's budget: the GS steps it trained
    if "naive" in args.rows:
        share_stages(out / "coin", out / "naive")
        rows["naive"] = coin_row(syn, scene_dir, out / "naive", naive)
        print(name, "naive", json.dumps(rows["naive"]), file=sys.stderr, flush=True)
    if "masked_recon" in args.rows:
        steps = args.masked_steps or naive.iters_refgs
        rows["masked_recon"] = masked_recon_row(syn, scene_dir, out / "masked_recon", steps, args.seed)
        print(name, "masked_recon", json.dumps(rows["masked_recon"]), file=sys.stderr, flush=True)
    if "coin_input" in args.rows:
        share_stages(out / "coin", out / "coin_input", ("0_scene",))
        rows["coin_input"] = coin_row(
            syn, scene_dir, out / "coin_input", replace(cfg, inpaint_region="input")
        )
        print(name, "coin_input", json.dumps(rows["coin_input"]), file=sys.stderr, flush=True)
    if "coin_view_check" in args.rows:
        share_stages(out / "coin", out / "coin_view_check", ("0_scene",))
        vc = replace(cfg, inpaint_region="refined", refine=VIEW_CHECK)
        rows["coin_view_check"] = coin_row(syn, scene_dir, out / "coin_view_check", vc)
        print(name, "coin_view_check", json.dumps(rows["coin_view_check"]), file=sys.stderr, flush=True)
    if "coin_no_bg_depth" in args.rows:
        share_stages(out / "coin", out / "coin_no_bg_depth")
        nobg = replace(cfg, refgs=RefGSConfig(bg_depth=False))
        rows["coin_no_bg_depth"] = coin_row(syn, scene_dir, out / "coin_no_bg_depth", nobg)
        print(name, "coin_no_bg_depth", json.dumps(rows["coin_no_bg_depth"]), file=sys.stderr, flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--budget", type=float, default=3.0,
                    help="CoIn's training minutes per run (the demo's before f4085d3, 2 since)")  # fmt: skip
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--size", type=int, nargs=2, default=(192, 144), help="width height (demo: 192 144)")
    ap.add_argument("--views", type=int, default=24, help="views per room (demo: 24)")
    steps = ("REFGS", "TED_FT", "TED_ADV")
    ap.add_argument("--iters", type=int, nargs=3, default=(591, 411, 499), metavar=steps,
                    help="explicit steps (default: the demo's plan on a quiet machine at budget 3; "
                    "0 0 0: the budget plan of this machine)")  # fmt: skip
    ap.add_argument("--prior-seconds", type=float, default=120.0, help="scene prior (demo: 120)")
    ap.add_argument("--seed", type=int, default=0,
                    help="every row's training seed (CoInConfig.seed, TrainConfig.seed)")  # fmt: skip
    ap.add_argument("--rows", nargs="+", default=list(ROWS[:4]), choices=ROWS,
                    help="rows besides coin (coin_view_check: 0_refine's view check)")  # fmt: skip
    ap.add_argument("--refine-vote", type=float, default=None,
                    help="RefineConfig.min_fraction of the CoIn rows (default: the config's)")  # fmt: skip
    ap.add_argument("--refine-grow", type=int, default=None,
                    help="RefineConfig.grow_px of the CoIn rows (default: the config's)")  # fmt: skip
    ap.add_argument("--mask-dilate", type=int, default=None,
                    help="CoInConfig.mask_dilate of the CoIn rows (default: the auto ring; 0: the exact "
                         "masks, docs/RESULTS.md 'Where the rooms' m-PSNR is decided')")  # fmt: skip
    ap.add_argument("--observed", default=CoInConfig.observed, choices=("target", "captures"),
                    help="CoInConfig.observed of the CoIn rows: how the observed part of a refined mask "
                         "reaches the model (default: the config's)")  # fmt: skip
    ap.add_argument("--masked-steps", type=int, default=None,
                    help="masked reconstruction's 3DGS steps (default: Ref-GS + TE-D's)")  # fmt: skip
    args = ap.parse_args()
    if not any(args.iters):
        args.iters = None
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    print(
        f"# rooms benchmark: CPU {cpu_model()}, commit {git_commit()}, budget {args.budget} min, "
        f"{args.size[0]}x{args.size[1]}, {args.views} views, steps {args.iters}, prior {args.prior_seconds} s"
    )
    all_rows = {name: run_scene(name, args.out / name, args) for name in args.scenes}

    def f(v, d=2):
        return "n/a" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.{d}f}"

    print(
        "\n| scene | row | region | PSNR | m-PSNR | m-PSNR obs. | m-PSNR unseen | HF ratio | bbox GMSD "
        "| m-VGG-PD | ghost | observed share (exact) | unseen core P / R | min |"
    )
    print("|---" * 14 + "|")
    for scene, rows in all_rows.items():
        for name, r in rows.items():
            share = (
                f"{f(r.get('observed_share'))} ({f(r.get('exact_observed_share'))})"
                if "precision" in r
                else "-"
            )
            pr = f"{f(r.get('precision'))} / {f(r.get('recall'))}" if "precision" in r else "-"
            print(
                f"| {scene} | {name} | {r['region']} | {f(r['psnr'])} | {f(r['m_psnr'])} "
                f"| {f(r['m_psnr_observed'])} | {f(r['m_psnr_unseen'])} | {f(r['hf_ratio'], 3)} "
                f"| {f(r['bbox_gmsd'], 3)} | {vgg_pd_cell(r.get('m_vgg_pd'))} | {f(r['ghost'], 3)} "
                f"| {share} | {pr} | {r['minutes']:.1f} |"
            )
    if any(r.get("m_vgg_pd") is None for rows in all_rows.values() for r in rows.values()):
        print(f"\nm-VGG-PD: {vgg_pd_note() or 'absent when these rows ran'}")
    result = {}
    for scene, rows in all_rows.items():
        for row in rows:
            result[f"{scene}_{row}_mpsnr"] = rows[row]["m_psnr"]
        if scene == "room" and "masked_recon" in rows:
            result.update(
                room_coin_hf_ratio=rows["coin"]["hf_ratio"],
                room_coin_gmsd=rows["coin"]["bbox_gmsd"],
                room_masked_recon_gmsd=rows["masked_recon"]["bbox_gmsd"],
                room_ghost=rows["coin"]["ghost"],
            )
    write_result(args.out, result, all_rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
