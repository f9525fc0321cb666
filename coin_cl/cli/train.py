"""`coin-cl train` and `coin-cl render`: Gaussian-splatting reconstruction of a scene folder."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from coin_cl.cli import values


def add_commands(subparsers) -> None:
    t = subparsers.add_parser("train", help="train vanilla 3DGS or Scaffold-GS on a scene folder")
    t.add_argument("scene_dir", type=Path)
    t.add_argument("--model", choices=("scaffold", "3dgs"), default="scaffold")
    t.add_argument("--iters", type=int, default=30_000)
    t.add_argument("--resolution", type=float, default=0.5, help="image scale (0.5 = half size)")
    t.add_argument(
        "--out",
        type=values.folder,
        required=True,
        help="output folder: new, empty, or one coin-cl train made (resumes if it has ckpt.pt)",
    )
    t.add_argument(
        "--holdout",
        type=int,
        default=8,
        help="hold out every Nth training view for evaluation (0: use the scene's test views)",
    )
    t.add_argument(
        "--targets",
        choices=("images", "inpainted"),
        default="images",
        help="train on the images, or on the per-view 2D inpaints (RGB_inpainted)",
    )
    t.add_argument("--exclude-masks", action="store_true", help="leave object masks out of the loss")
    t.add_argument("--max-minutes", type=float, default=0.0, help="stop after this much training time")
    t.add_argument("--eval-every", type=int, default=0)
    t.add_argument("--ckpt-every", type=int, default=1000)
    t.add_argument("--backend", choices=("opencl", "torch"), default="opencl")
    t.add_argument("--device", default=None, help="OpenCL device name substring (default: coin-cl doctor's)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint in --out")
    t.add_argument(
        "--fused", choices=("on", "off"), default="on",
        help="fused training path (default); 'off' runs the earlier unfused one (for comparisons)",
    )  # fmt: skip
    t.set_defaults(func=cmd_train)

    r = subparsers.add_parser("render", help="render a trained model: images, depth maps, an orbit")
    r.add_argument("out_dir", type=Path, help="a folder coin-cl train or coin-cl run made")
    r.add_argument(
        "--out",
        type=Path,
        default=None,
        help="write the renders here (new, empty, or one coin-cl render made) instead of OUT_DIR/renders",
    )
    r.add_argument("--views", choices=("test", "train", "orbit"), default="test")
    r.add_argument("--frames", type=int, default=48, help="orbit frames")
    r.add_argument("--scale", type=values.scale_or_capture, default=1.0,
                   help="image size over the cameras' (a run folder's are at its working resolution); "
                   "'capture': a run's photos' own size")  # fmt: skip
    r.add_argument("--backend", choices=("opencl", "torch"), default="opencl")
    r.add_argument("--device", default=None, help="OpenCL device name substring (default: coin-cl doctor's)")
    r.set_defaults(func=cmd_render)


def cmd_train(args: argparse.Namespace) -> int:
    from coin_cl import load_scene
    from coin_cl.cli.guard import output_folder
    from coin_cl.gs.model_kinds import scaled_model_config
    from coin_cl.gs.trainer import TrainConfig, make_trainer
    from coin_cl.scene.splits import inpainted_targets, split_indices

    scene = load_scene(args.scene_dir, resolution=args.resolution)
    tr_idx, te_idx = split_indices(scene, args.holdout)
    images = inpainted_targets(scene) if args.targets == "inpainted" else None
    cfg = TrainConfig(
        model=args.model,
        iters=args.iters,
        backend=args.backend,
        seed=args.seed,
        eval_every=args.eval_every,
        ckpt_every=args.ckpt_every,
        max_seconds=60.0 * args.max_minutes,
        fused=args.fused == "on",
    )
    with output_folder(args.out, "train"):
        tr = make_trainer(
            scene, tr_idx, te_idx, cfg, args.out, images,
            scaled_model_config(args.model, args.iters), args.exclude_masks, resume=not args.fresh,
            device=args.device,
        )  # fmt: skip
        res = tr.train()
    print(
        f"{args.model}: {res['step']} steps in {res['train_seconds']:.0f} s, "
        f"{res['n']} primitives, held-out PSNR {res.get('psnr', math.nan):.2f} dB "
        f"SSIM {res.get('ssim', math.nan):.4f}; wrote {args.out}"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from coin_cl.cli.guard import output_folder
    from coin_cl.outdir import MARKER, OutputFolderError, check_output, read_marker
    from coin_cl.render_utils import render_checkpoint

    if args.out_dir.is_file() and args.out_dir.suffix.lower() == ".ply":
        from coin_cl.gs.splats import Splats

        g = Splats.from_ply(args.out_dir)  # a truncated or malformed file: one line naming it
        raise ValueError(
            f"{args.out_dir} holds {len(g)} Gaussians but no cameras: render the folder it was trained "
            "into (or a coin-cl run folder); to open the PLY in a viewer see `coin-cl export`"
        )

    src = args.out_dir
    if not src.is_dir():
        raise FileNotFoundError(f"{src} is not a folder: give a folder coin-cl train or coin-cl run made")
    if args.out is not None and args.out.resolve().is_relative_to(src.resolve()):
        raise OutputFolderError(
            f"--out {args.out} lies inside {src}: leave --out out to render into {src / 'renders'}"
        )
    if args.out is not None:
        # the trained folder is only read; the renders go to a folder of render's own
        folder, command, dest = args.out, "render", args.out
    else:
        # the renders go inside the trained folder: only one its command made, taken like that command
        made_by = (read_marker(src) or {}).get("command")
        command = made_by or ("run" if (src / "run.json").is_file() else "train")
        try:
            kind = check_output(src, command) if command in ("train", "run") else None
        except OutputFolderError:
            kind = None
        if kind != "ours":
            raise OutputFolderError(
                f"{src} is the output folder of coin-cl {made_by}: give render a folder coin-cl train "
                "or coin-cl run made"
                if made_by
                else f"{src} has no model to render (no ckpt.pt, run.json or {MARKER} in it): train "
                "into it first, or give a folder coin-cl train or coin-cl run made"
            )
        folder, dest = src, src / "renders"
    with output_folder(folder, command):
        n, where = render_checkpoint(
            src, args.views, args.frames, args.backend, args.device, dest, args.scale
        )
    if args.views == "orbit":
        print(f"wrote {n} frames and {where}")
    else:
        print(f"wrote {n} images and depth maps to {where}")
    return 0
