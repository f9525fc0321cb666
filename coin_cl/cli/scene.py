"""`coin-cl make-scene` (the embedded ground-truth scene, or with --from-capture a real capture with a
virtual box painted in: `coin_cl.prepare.virtual_scene`) and `coin-cl eval` (metrics of predicted
test views against a scene's object-absent ground truth)."""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_cl.cli import values


def add_commands(subparsers) -> None:
    """Register make-scene and eval on the `coin-cl` subparsers."""
    p = subparsers.add_parser(
        "make-scene",
        help="generate the synthetic room scene with ground truth, or (--from-capture) a removal scene "
        "from a posed real capture with a virtual box painted into its training views",
    )
    p.add_argument("out_dir", type=values.folder, nargs="?", default=None, help="folder to write (or --out)")
    p.add_argument("--out", type=values.folder, default=None, help="folder to write (same as OUT_DIR)")
    p.add_argument("--from-capture", type=Path, default=None, metavar="CAPTURE",
                   help="posed capture folder (COLMAP / SPIn-NeRF layout, pinhole cameras): paint a virtual "
                        "box into its training views; every --test-every-th view stays untouched as a test "
                        "view (docs/VIRTUAL_OBJECTS.md)")  # fmt: skip
    p.add_argument("--box", type=float, nargs=6, default=None, metavar=("CX", "CY", "CZ", "SX", "SY", "SZ"),
                   help="with --from-capture: a point the box stands near (capture's world frame; its base "
                        "goes on the surface fitted there) and its extents (x, y, up)")  # fmt: skip
    p.add_argument(
        "--yaw", type=float, default=0.0, help="with --box: turn about the surface normal, degrees"
    )
    p.add_argument(
        "--auto", action="store_true", help="with --from-capture: choose the placement automatically"
    )
    p.add_argument(
        "--test-every", type=int, default=8, help="with --from-capture: every K-th view is a test view"
    )
    p.add_argument("--coverage", type=int, default=180, choices=(90, 180, 360), help="camera arc in degrees")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=40, help="number of views (a quarter are test views)")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--task", choices=("removal", "insertion"), default="removal",
                   help="removal: capture with the object, target without; insertion: capture without, "
                        "target with a red box on the table, masks = its footprint")  # fmt: skip
    p.set_defaults(func=cmd_make_scene)

    e = subparsers.add_parser(
        "eval", help="PSNR/SSIM (+ masked; LPIPS, VGG-PD when weights exist) of test views"
    )
    e.add_argument("pred_dir", type=Path, help="one image per test view, named as the view")
    e.add_argument("--scene", type=Path, required=True, help="scene folder with ground truth")
    e.add_argument(
        "--out",
        type=values.folder,
        default=None,
        help="output folder (default PRED_DIR/eval): new, empty, or one coin-cl eval made",
    )
    e.set_defaults(func=cmd_eval)


def cmd_make_scene(args: argparse.Namespace) -> int:
    if args.out_dir is not None and args.out is not None and args.out_dir != args.out:
        raise ValueError(f"two output folders given ({args.out_dir} and --out {args.out}); give one")
    out_dir = args.out or args.out_dir
    if out_dir is None:
        raise ValueError("no output folder: give OUT_DIR or --out")
    if args.from_capture is not None:
        return _make_from_capture(args, out_dir)
    if args.box is not None or args.auto:
        raise ValueError("--box and --auto place a virtual object in a capture: add --from-capture CAPTURE")
    from coin_cl.cli.guard import output_folder
    from coin_cl.scene.synthetic import write_synthetic

    with output_folder(out_dir, "make-scene"):
        out = write_synthetic(
            out_dir,
            coverage=args.coverage,
            seed=args.seed,
            n_views=args.views,
            width=args.width,
            height=args.height,
            task=args.task,
        )
    print(f"wrote synthetic {args.task} scene ({args.views} views, coverage {args.coverage} deg) to {out}")
    return 0


def _make_from_capture(args: argparse.Namespace, out_dir: Path) -> int:
    from coin_cl.outdir import mark_output
    from coin_cl.prepare.virtual_scene import BoxSpec, VirtualSceneConfig, make_virtual_scene

    if (args.box is None) == (not args.auto):
        raise ValueError("--from-capture needs a placement: --box CX CY CZ SX SY SZ [--yaw DEG] or --auto")
    spec = None if args.auto else BoxSpec(tuple(args.box[:3]), tuple(args.box[3:]), args.yaw)
    cfg = VirtualSceneConfig(test_every=args.test_every, seed=args.seed)
    # make_virtual_scene refuses a non-empty OUT and writes it through a scratch folder renamed at
    # the end; the marker then makes it make-scene's folder like any other output folder.
    doc = make_virtual_scene(args.from_capture, out_dir, spec, cfg)
    mark_output(out_dir, "make-scene")
    n, cov = doc["n_views"], doc["coverage_train"]
    print(
        f"wrote {out_dir}: {n['train']} training views (box painted; coverage median "
        f"{100 * cov.get('median', 0):.1f}%), {n['test']} test views, {n['excluded']} excluded (box hidden); "
        f"{doc['points']['kept']} sparse points; {doc['seconds']['total']:.0f} s"
    )
    b = doc["box"]
    print(f"box: centre {[round(x, 4) for x in b['center']]}, size {[round(x, 4) for x in b['size']]}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from coin_cl.cli.guard import output_folder
    from coin_cl.evaluation import evaluate_folder, fmt_metric

    out = args.out or args.pred_dir / "eval"
    with output_folder(out, "eval"):
        doc = evaluate_folder(args.pred_dir, args.scene, out)
    m = doc["mean"]
    print(
        f"{doc['n_views']} views: PSNR {fmt_metric(m['psnr'])}  SSIM {fmt_metric(m['ssim'])}  "
        f"m-PSNR {fmt_metric(m['m_psnr'])}  m-SSIM {fmt_metric(m['m_ssim'])}  LPIPS {fmt_metric(m['lpips'])}"
        f"  SWD {fmt_metric(m.get('swd'))}  colour {fmt_metric(m.get('color_dist'))}"
        f"  VGG-PD {fmt_metric(m.get('vgg_pd'))}  m-VGG-PD {fmt_metric(m.get('m_vgg_pd'))}"
    )
    if m.get("vgg_pd") is None:
        print(doc["vgg_pd"])
    print(f"wrote {out / 'metrics.json'}, {out / 'metrics.md'}, {out / 'grids'}/")
    return 0
