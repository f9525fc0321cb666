"""Stage 0_refine's observed / unseen split against the ray-cast truth, by removal vote
(`RefineConfig.min_fraction`) and split rule, on the demo room or the 360-degree room.

For each vote, G^rmv is pruned from one object-present fit (591 steps, the demo's Ref-GS count;
fitted once in OUT/gs and reused) and rendered into the training views; each rule then splits the
input masks. Columns: the observed share found (exact: `rooms.split_scores`' figure), precision and
recall of the exactly unseen core, the share of exactly observed pixels marked unseen, the PSNR of
the observed part's target (R^rmv_n, or the captures warped with `warp_tol`) against the exact
object-free views on the pixels marked observed (the error of what stage 1 and Ref-GS are handed
as observed background), and the seconds of the pruning + renders and of the split.

    python benchmarks/refine_split.py --out OUT --scene room [--votes 0.5 0.9 1.0] [--rules grow1 grow0]

The last line is JSON: per vote, the default rule's (grow0) precision, recall and target PSNR.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from common import cpu_model, git_commit, write_result
from rooms import SCENES, split_counts

from coin_cl.metrics import masked_psnr
from coin_cl.pipeline.refine_masks import RefineConfig, fit_renders, split_view
from coin_cl.scene import load_scene
from coin_cl.scene.masks import derive_mask
from coin_cl.scene.synthetic import make_synthetic, truly_unseen, write_synthetic

RULES = {  # the growth given explicitly: the rows measured before its default changed (1 -> 0)
    "grow1": {"grow_px": 1},
    "grow0": {"grow_px": 0},
    "no_see_through": {"see_through": 0.0, "grow_px": 1},
    "view_check": {"view_check": 0.05, "see_through": 0.0, "grow_px": 0},
    "warp": {"warp_tol": 0.03, "grow_px": 1},
}


def scores(syn, scene, masks, train, renders, truth, cfg: RefineConfig) -> dict:
    """The split of every training view by `cfg`, scored against the ray-cast `truth`
    (`rooms.split_counts`), plus the observed target's PSNR on the pixels marked observed."""
    found, psnr = {}, []
    for n in train:
        r, warped, hit = split_view(scene, masks, renders, n, train, cfg)
        found[n] = r
        o = masks[n] & ~r
        target = renders[n][0] if warped is None else np.where(hit[..., None], warped, renders[n][0])
        if o.any():
            psnr.append(masked_psnr(target, syn.absent[n], o))
    return {**split_counts(syn, found, truth), "target_psnr": float(np.mean(psnr))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scene", default="room", choices=list(SCENES))
    ap.add_argument("--votes", type=float, nargs="+", default=[0.5, 0.75, 0.9, 1.0])
    ap.add_argument("--rules", nargs="+", default=list(RULES), choices=list(RULES))
    ap.add_argument("--iters", type=int, default=591, help="the object-present fit's steps (demo: 591)")
    args = ap.parse_args()

    syn = make_synthetic(coverage=SCENES[args.scene], n_views=24, width=192, height=144, seed=0)
    scene_dir = args.out / "scene"
    if not (scene_dir / "views.txt").is_file():
        write_synthetic(scene_dir, syn)
    scene = load_scene(scene_dir)
    train = list(scene.train_idx)
    # the training masks as the pipeline hands them over: the auto dilation at 192x144 is one 5x5 step
    masks = [
        derive_mask(m, "seg", dilate=1) if i in train and m.any() else m for i, m in enumerate(scene.masks)
    ]
    truth = truly_unseen(syn, train)  # ray cast once, for every vote and rule
    print(f"# {args.scene}: {len(train)} training views, 192x144; CPU {cpu_model()}; commit {git_commit()}")
    print(f"{'vote':>5} | {'rule':<16} | observed (exact) | precision | recall | obs. marked unseen | "
          f"target dB | s render | s split")  # fmt: skip
    rows, summary = {}, {"scene": args.scene}
    for vote in args.votes:
        t = time.perf_counter()
        renders, _, _ = fit_renders(scene, masks, train, args.out / "gs", RefineConfig(min_fraction=vote),
                                    args.iters)  # fmt: skip
        t_render = time.perf_counter() - t
        for rule in args.rules:
            t = time.perf_counter()
            cfg = RefineConfig(min_fraction=vote, **RULES[rule])
            s = scores(syn, scene, masks, train, renders, truth, cfg)
            t_split = time.perf_counter() - t
            rows[f"{vote} {rule}"] = {**s, "s_render": t_render, "s_split": t_split}
            share = f"{s['observed_share']:.3f} ({s['exact_observed_share']:.3f})"
            cells = [f"{vote:>5}", f"{rule:<16}", share,
                     f"{s['precision']:.3f}", f"{s['recall']:.3f}", f"{s['observed_marked_unseen']:.3f}",
                     f"{s['target_psnr']:.2f}", f"{t_render:.1f}", f"{t_split:.1f}"]  # fmt: skip
            print(" | ".join(cells), flush=True)
            if rule == "grow0":  # the default rule
                summary[f"vote_{vote}"] = {k: round(s[k], 3) for k in ("precision", "recall", "target_psnr")}
    write_result(args.out, summary, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
