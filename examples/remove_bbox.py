"""Remove an object from your own scene given only bounding boxes.

    python examples/remove_bbox.py path/to/scene --out runs/mine [--ref IMG_0012.jpg] [--budget 10]
        [--iters N --prior-seconds S]   # fixed small counts instead of the budget (smoke runs)

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
    ap.add_argument("--budget", type=float, default=10.0)
    ap.add_argument("--resolution", type=float, default=None, help="default: from the image size")
    ap.add_argument("--iters", type=int, default=None, help="explicit iterations per training stage")
    ap.add_argument("--prior-seconds", type=float, default=None, help="scene prior training (smoke runs)")
    args = ap.parse_args(argv)

    scene = coin_cl.load_scene(args.scene)
    cfg = CoInConfig(resolution=args.resolution, prior_seconds=args.prior_seconds).with_iters(args.iters)
    ref = int(args.ref) if args.ref is not None and args.ref.isdigit() else args.ref
    result = coin_cl.inpaint(scene, args.out, mask_kind="bbox", reference=ref, budget=args.budget, config=cfg)
    print(f"final Gaussians: {result.ply}")
    return result


if __name__ == "__main__":
    main()
