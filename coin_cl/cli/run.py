"""`coin-cl run`: CoIn end to end on a scene (a thin parser over `coin_cl.pipeline.coin.inpaint`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="CoIn on a scene: 2D inpainting, Ref-GS, CLG, TE-D, evaluation")
    p.add_argument("scene", type=Path, help="a folder load_scene reads (SPIn-NeRF, COLMAP, coin-cl)")
    p.add_argument("--out", type=Path, required=True, help="run folder (a rerun resumes)")
    p.add_argument("--mask", choices=("seg", "bbox", "scribble"), default="seg")
    p.add_argument("--masks", choices=("input", "refined"), default="input",
                   help="refined: 3D-first (wide/360 captures, removal): inpaint only the mask pixels no "
                        "other view sees (stage 0_refine)")  # fmt: skip
    p.add_argument("--ref", default=None, help="reference view, name or index (default: chosen by rule)")
    p.add_argument("--prompt", default="", help="text for insertion (needs --sd-path or COIN_SD2_PATH)")
    p.add_argument("--edited-ref", type=Path, default=None,
                   help="insertion without weights: the reference view edited in a 2D tool (the object "
                        "painted in; the masks cover where it goes in every view); its view is --ref or "
                        "the one it matches")  # fmt: skip
    p.add_argument("--budget", type=float, default=30.0, help="training minutes to aim at")
    p.add_argument("--resolution", type=float, default=1.0, help="image scale (0.5 = half)")
    p.add_argument("--skip-stage", action="append", default=[], choices=("refgs", "clg", "ted"),
                   help="leave a stage out (the paper's ablations); repeatable")  # fmt: skip
    p.add_argument(
        "--iters", type=int, default=None, help="iterations of each training stage (overrides --budget)"
    )
    p.add_argument(
        "--prior-seconds",
        type=float,
        default=None,
        help="training seconds of the embedded scene prior (overrides --budget; >= 120 to be useful)",
    )
    p.add_argument("--sd-path", default=None, help="Stable Diffusion 2 inpainting folder (diffusers format)")
    p.add_argument("--inpainter", choices=("auto", "embedded", "telea", "lama"), default="auto",
                   help="stage 1 without SD2 or dataset inpaints: auto = lama when a file is named, else "
                        "embedded (exemplar patches + smooth structure, no weights)")  # fmt: skip
    p.add_argument("--lama-path", default=None, help="LaMa TorchScript big-lama.pt (or COIN_LAMA_PATH)")
    p.add_argument("--dino-path", default=None, help="DINO ViT-S/16 checkpoint")
    p.add_argument("--device", default=None, help="OpenCL device name substring")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="append", default=[], help="rerun this stage folder (e.g. 3_clg)")
    p.set_defaults(func=cmd_run)


def cmd_run(args: argparse.Namespace) -> int:
    from coin_cl.pipeline.coin import CoInConfig, inpaint
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig

    i2d = Inpaint2DConfig(inpainter=args.inpainter, lama_path=args.lama_path)
    cfg = CoInConfig(
        resolution=args.resolution, sd_path=args.sd_path, dino_path=args.dino_path,
        skip=tuple(args.skip_stage), seed=args.seed, device=args.device, prior_seconds=args.prior_seconds,
        masks=args.masks, inpaint2d=i2d,
    ).with_iters(args.iters)  # fmt: skip
    ref = int(args.ref) if args.ref is not None and args.ref.isdigit() else args.ref
    res = inpaint(args.scene, args.out, masks=args.mask, reference=ref, prompt=args.prompt or None,
                  budget=args.budget, config=cfg, force=tuple(args.force),
                  edited_ref=args.edited_ref)  # fmt: skip
    for name, rec in res.stages.items():
        print(f"  {name}: {rec['status']}" + (f" ({rec['seconds']:.0f} s)" if "seconds" in rec else ""))
    if res.metrics:
        print(
            json.dumps(
                {k: res.metrics.get(k) for k in ("psnr", "ssim", "m_psnr", "m_ssim", "hf_ratio", "bbox_gmsd")}
            )
        )
    print(f"wrote {args.out}/ (final Gaussians {res.ply}, renders {res.renders}, log.json)")
    return 0
