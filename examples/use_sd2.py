"""Use your own Stable Diffusion 2 inpainting weights (a diffusers-format folder) in CoIn.

    python examples/use_sd2.py path/to/scene --sd-path path/to/stable-diffusion-2-inpainting --out runs/sd2
        [--prompt "a red apple"]     # insertion from text (SD2 only); empty prompt = removal

The folder must hold what `save_pretrained` writes (unet/, vae/, text_encoder/, tokenizer/,
scheduler/, model_index.json); nothing is downloaded. `coin-cl doctor` says whether it is complete.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_cl.diffusion.sd2 import check_sd2_folder

import coin_cl
from coin_cl.pipeline.coin import CoInConfig


def main(argv: list[str] | None = None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--sd-path", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--prompt", default="")
    ap.add_argument("--mask-kind", choices=("seg", "bbox", "scribble"), default="seg")
    ap.add_argument("--budget", type=float, default=30.0)
    args = ap.parse_args(argv)

    check_sd2_folder(args.sd_path)  # names the missing file before any work starts
    cfg = CoInConfig(sd_path=str(args.sd_path))
    result = coin_cl.inpaint(coin_cl.load_scene(args.scene), args.out, mask_kind=args.mask_kind,
                             prompt=args.prompt, budget=args.budget, config=cfg)  # fmt: skip
    print(f"final Gaussians: {result.ply}")
    return result


if __name__ == "__main__":
    main()
