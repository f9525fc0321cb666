"""Remove an object from your own scene given only bounding boxes.

    python examples/remove_bbox.py path/to/scene --out runs/mine [--ref IMG_0012.jpg] [--budget 30]

The scene is a COLMAP folder with object masks in masks/<image name> (or any layout `load_scene`
reads); each mask is replaced by its bounding box, the shape a user draws in a viewer.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import coin_cl
from coin_cl.pipeline.coin import CoInConfig


def main(argv: list[str] | None = None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--ref", default=None, help="reference view (name or index); default chosen by rule")
    ap.add_argument("--budget", type=float, default=30.0)
    ap.add_argument("--resolution", type=float, default=None, help="default: from the image size")
    ap.add_argument("--iters", type=int, default=None, help="explicit iterations per training stage")
    args = ap.parse_args(argv)

    scene = coin_cl.load_scene(args.scene)
    cfg = CoInConfig(resolution=args.resolution)
    if args.iters is not None:
        cfg.iters_refgs = cfg.iters_ted_finetune = cfg.iters_ted_adversarial = args.iters
    ref = int(args.ref) if args.ref is not None and args.ref.isdigit() else args.ref
    result = coin_cl.inpaint(scene, args.out, mask_kind="bbox", reference=ref, budget=args.budget, config=cfg)
    print(f"final Gaussians: {result.ply}")
    return result


if __name__ == "__main__":
    main()
