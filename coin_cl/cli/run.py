"""`coin-cl run`: CoIn end to end on a scene (a thin parser over `coin_cl.pipeline.coin.inpaint`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_cl.cli import values
from coin_cl.pipeline.insert_config import PROFILES

# --clg's choices: the CLGConfig fields each sets (auto: CLGConfig's defaults)
CLG_MODES = {"auto": {}, "propagate": {"without_sampler": True}, "prior": {"prior_sampler": True}}


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="CoIn on a scene: 2D inpainting, Ref-GS, CLG, TE-D, evaluation")
    p.add_argument("scene", type=Path, help="a folder load_scene reads (SPIn-NeRF, COLMAP, coin-cl)")
    p.add_argument(
        "--out",
        type=values.folder,
        required=True,
        help="run folder: new, empty, or one coin-cl run made (a rerun resumes); another folder is refused",
    )
    p.add_argument("--mask-kind", choices=("seg", "bbox", "scribble"), default="seg",
                   help="the shape of the object's masks: the scene's segmentation, or its bounding box / "
                        "scribbles derived from it (default seg)")  # fmt: skip
    p.add_argument("--mask-dilate", type=int, default=None, metavar="N",
                   help="dilate the training masks N times with a 5x5 kernel (2 px each); default: a "
                        "ring of 1.4%% of the longer side, as SPIn-NeRF's masks; 0 = the masks as "
                        "given, for exact masks (the refined split's removal vote still uses the "
                        "ring)")  # fmt: skip
    p.add_argument("--inpaint-region", choices=("auto", "input", "refined"), default="auto",
                   help="input: inpaint the whole masks; refined: 3D-first (wide/360 captures, "
                        "removal): inpaint only the mask pixels no other view sees (stage 0_refine); "
                        "auto (default): refined when other views see at least 30%% of the masks "
                        "(estimated, logged)")  # fmt: skip
    p.add_argument("--carve", action="store_true",
                   help="removal: carve the object's volume out of the Gaussians for good and seed the "
                        "background behind it (coin_cl.gs.carve; experimental, off by default)")  # fmt: skip
    p.add_argument("--ref", default=None,
                   help="reference view: a view name (with or without extension) or an index; a name that "
                        "exists wins (default: chosen by rule)")  # fmt: skip
    p.add_argument("--prompt", default="", help="text for insertion (needs --sd-path or COIN_SD2_PATH)")
    p.add_argument("--edited-ref", type=Path, default=None,
                   help="insertion without weights: the reference view edited in a 2D tool (the object "
                        "painted in); its view is --ref or the one it matches")  # fmt: skip
    p.add_argument("--insert-regions", choices=("auto", "hull", "derive"), default="auto",
                   help="with --edited-ref: derive = the object is stood on the surface under the edit "
                        "and every other view's region is derived (no masks needed); hull = the masks "
                        "cover it in every view; auto = hull when every training view has a mask, else "
                        "derive")  # fmt: skip
    p.add_argument("--insert-profile", choices=PROFILES, default="revolve",
                   help="with derived regions: the object's shape behind its silhouette; revolve = a "
                        "solid of revolution about the vertical (round objects, and the safe choice), "
                        "extrude = a prism as deep as 0.65 of its width (a box seen face-on), rounded = "
                        "a prism thinner toward its outline")  # fmt: skip
    p.add_argument("--budget", type=values.positive_float, default=10.0,
                   help="the run's wall-clock minutes, every stage and eval included; timing probes turn "
                        "them into steps, recorded in OUT/plan.json; a budget this machine cannot fit is "
                        "refused with the minimum (default 10; docs/RUN.md, 'The budget')")  # fmt: skip
    p.add_argument("--resolution", type=values.positive_float, default=None,
                   help="image scale (0.5 = half); default: picked from the image size (at most "
                        "160k pixels a view, logged)")  # fmt: skip
    p.add_argument("--skip-stage", action="append", default=[], choices=("refgs", "clg", "ted"),
                   help="the paper's ablations, repeatable: clg / ted leave that stage out; refgs trains the "
                        "coarse GS (stage 2_refgs, which CLG and TE-D stand on) as plain Scaffold-GS, "
                        "without Ref-GS's four pieces")  # fmt: skip
    p.add_argument("--clg", choices=tuple(CLG_MODES), default="auto",
                   help="CLG's sampler: auto = Stable Diffusion 2 with --sd-path, else CLG is left out "
                        "(logged; its propagation alone scored below leaving it out on real scenes); "
                        "propagate = no sampler, each view's hole takes the reference's answer warped "
                        "into it where that is no worse; prior = the embedded scene prior's sampler "
                        "(minutes of training; docs/RUN.md)")  # fmt: skip
    p.add_argument("--iters", type=values.positive_int, default=None,
                   help="steps of each GS training stage (replaces the budget's plan)")  # fmt: skip
    p.add_argument("--prior-seconds", type=values.nonneg_float, default=None,
                   help="training seconds of the embedded scene prior (replaces the budget's share; >= 120 "
                        "to be useful)")  # fmt: skip
    p.add_argument("--sd-path", default=None, help="Stable Diffusion 2 inpainting folder (diffusers format)")
    p.add_argument("--sd2-mode", choices=("auto", "reference_only", "all"), default="auto",
                   help="with --sd-path: all = SD2 on every view (paper), reference_only = SD2 on the "
                        "reference, the other views from it through the warp + the embedded inpainter "
                        "(CPU-practical); auto = reference_only on a CPU when SD2 on every view is "
                        "estimated above 2 h (logged with the estimate)")  # fmt: skip
    p.add_argument("--inpainter", choices=("auto", "embedded", "telea", "lama"), default="auto",
                   help="stage 1 without SD2 or dataset inpaints: auto = lama when a file is named, else "
                        "embedded (exemplar patches + smooth structure, no weights)")  # fmt: skip
    p.add_argument("--lama-path", type=values.existing_file, default=None,
                   help="LaMa TorchScript big-lama.pt (or COIN_LAMA_PATH). TorchScript is a program: "
                        "the file runs as code, so name only a file you trust (IOPaint's own)")  # fmt: skip
    p.add_argument("--dino-path", default=None, help="DINO ViT-S/16 checkpoint")
    p.add_argument("--device", default=None, help="OpenCL device name substring")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="append", default=[],
                   help="rerun this stage even if up to date: a folder name (3_clg) or its short name "
                        "(clg)")  # fmt: skip
    p.set_defaults(func=cmd_run)


def cmd_run(args: argparse.Namespace) -> int:
    from coin_cl.cli.guard import output_folder

    # The folder is checked and locked before the pipeline (and torch) is imported: a refusal (a
    # folder another command holds, a planted link) comes in a fraction of a second.
    with output_folder(args.out, "run"):
        from coin_cl.pipeline.clg import CLGConfig
        from coin_cl.pipeline.coin import CoInConfig, inpaint
        from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
        from coin_cl.pipeline.insert_config import InsertConfig
        from coin_cl.pipeline.report import run_report
        from coin_cl.report_html import write_report

        i2d = Inpaint2DConfig(inpainter=args.inpainter, lama_path=args.lama_path, sd2_mode=args.sd2_mode)
        clg = CLGConfig(**CLG_MODES[args.clg]) if CLG_MODES[args.clg] else None
        cfg = CoInConfig(clg=clg,
            resolution=args.resolution, sd_path=args.sd_path, dino_path=args.dino_path,
            mask_dilate=args.mask_dilate,
            skip=tuple(args.skip_stage), seed=args.seed, device=args.device, prior_seconds=args.prior_seconds,
            inpaint_region=args.inpaint_region, carve=args.carve, inpaint2d=i2d,
            insert=InsertConfig(regions=args.insert_regions, profile=args.insert_profile),
        ).with_iters(args.iters)  # fmt: skip
        res = inpaint(args.scene, args.out, mask_kind=args.mask_kind, reference=args.ref,
                      prompt=args.prompt or None, budget=args.budget, config=cfg,
                      force=tuple(args.force), edited_ref=args.edited_ref)  # fmt: skip
        write_report(res.out)
    print(run_report(res))
    return 0
