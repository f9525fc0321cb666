"""`coin-cl make-scene` (the embedded ground-truth scene) and `coin-cl eval` (metrics of predicted
test views against a scene's object-absent ground truth)."""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_cl.cli import values


def add_commands(subparsers) -> None:
    """Register make-scene and eval on the `coin-cl` subparsers."""
    p = subparsers.add_parser("make-scene", help="generate the synthetic room scene with ground truth")
    p.add_argument("out_dir", type=values.folder, help="folder to write (SPIn-NeRF layout)")
    p.add_argument("--coverage", type=int, default=180, choices=(90, 180, 360), help="camera arc in degrees")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=40, help="number of views (a quarter are test views)")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--task", choices=("removal", "insertion"), default="removal",
                   help="removal: capture with the object, target without; insertion: capture without, "
                        "target with a red box on the table, masks = its footprint")  # fmt: skip
    p.set_defaults(func=cmd_make_scene)

    e = subparsers.add_parser("eval", help="PSNR/SSIM (+ masked, LPIPS when weights exist) of test views")
    e.add_argument("pred_dir", type=Path, help="one image per test view, named as the view")
    e.add_argument("--scene", type=Path, required=True, help="scene folder with ground truth")
    e.add_argument("--out", type=values.folder, default=None, help="output folder (default PRED_DIR/eval)")
    e.set_defaults(func=cmd_eval)


def cmd_make_scene(args: argparse.Namespace) -> int:
    from coin_cl.scene.synthetic import write_synthetic

    out = write_synthetic(
        args.out_dir,
        coverage=args.coverage,
        seed=args.seed,
        n_views=args.views,
        width=args.width,
        height=args.height,
        task=args.task,
    )
    print(f"wrote synthetic {args.task} scene ({args.views} views, coverage {args.coverage} deg) to {out}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from coin_cl.evaluation import evaluate_folder, fmt_metric

    doc = evaluate_folder(args.pred_dir, args.scene, args.out)
    out = args.out or args.pred_dir / "eval"
    m = doc["mean"]
    print(
        f"{doc['n_views']} views: PSNR {fmt_metric(m['psnr'])}  SSIM {fmt_metric(m['ssim'])}  "
        f"m-PSNR {fmt_metric(m['m_psnr'])}  m-SSIM {fmt_metric(m['m_ssim'])}  LPIPS {fmt_metric(m['lpips'])}"
        f"  SWD {fmt_metric(m.get('swd'))}  colour {fmt_metric(m.get('color_dist'))}"
    )
    print(f"wrote {out / 'metrics.json'}, {out / 'metrics.md'}, {out / 'grids'}/")
    return 0
