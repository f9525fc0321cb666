"""Use your own Stable Diffusion 2 inpainting weights (a diffusers-format folder) in CoIn.

    python examples/use_sd2.py path/to/scene --sd-path path/to/stable-diffusion-2-inpainting --out runs/sd2
        [--prompt "a red apple"]     # insertion from text (SD2 only); empty prompt = removal
        [--iters N --sd-steps N --sd-crop PX --clg-steps N --skip-stage clg]   # smoke runs

The folder must hold what `save_pretrained` writes (unet/, vae/, text_encoder/, tokenizer/,
scheduler/, model_index.json); nothing is downloaded. `coin-cl doctor` says whether it is complete.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from coin_cl.diffusion.sd2 import check_sd2_folder

import coin_cl
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig


def main(argv: list[str] | None = None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--sd-path", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--prompt", default="")
    ap.add_argument("--mask-kind", choices=("seg", "bbox", "scribble"), default="seg")
    ap.add_argument("--budget", type=float, default=10.0)
    ap.add_argument("--resolution", type=float, default=None, help="default: from the image size")
    ap.add_argument("--iters", type=int, default=None, help="explicit iterations per training stage")
    ap.add_argument("--sd-steps", type=int, default=None, help="DDIM steps of the 2D inpaints (paper: 50)")
    ap.add_argument("--sd-crop", type=int, default=None, help="crop side of the 2D inpaints (paper: 512)")
    ap.add_argument("--clg-steps", type=int, default=None, help="CLG's DDIM steps (paper: 200)")
    ap.add_argument("--sd2-mode", choices=("auto", "reference_only", "all"), default="auto",
                    help="SD2 on every view or the reference only (auto: by the CPU estimate)")  # fmt: skip
    ap.add_argument("--skip-stage", action="append", default=[], choices=("refgs", "clg", "ted"),
                    help="leave a stage out (the paper's ablations), repeatable")  # fmt: skip
    args = ap.parse_args(argv)

    check_sd2_folder(args.sd_path)  # names the missing file before any work starts
    clg = CLGConfig(steps=args.clg_steps)
    cfg = CoInConfig(
        sd_path=str(args.sd_path), resolution=args.resolution, clg=clg, skip=tuple(args.skip_stage)
    )
    inp = cfg.inpaint2d.inpaint
    if args.sd_steps is not None:
        inp = replace(inp, sampler_sd=replace(inp.sampler_sd, num_steps=args.sd_steps))
    if args.sd_crop is not None:
        inp = replace(inp, sd_crop=args.sd_crop)
    cfg = replace(cfg, inpaint2d=replace(cfg.inpaint2d, inpaint=inp, sd2_mode=args.sd2_mode))
    cfg = cfg.with_iters(args.iters)
    result = coin_cl.inpaint(coin_cl.load_scene(args.scene), args.out, mask_kind=args.mask_kind,
                             prompt=args.prompt, budget=args.budget, config=cfg)  # fmt: skip
    print(f"final Gaussians: {result.ply}")
    return result


if __name__ == "__main__":
    main()
