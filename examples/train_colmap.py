"""Train Gaussian Splatting on a COLMAP folder (images/ + sparse/0/) and render its held-out views.

    python examples/train_colmap.py path/to/colmap_scene --out runs/scene [--model scaffold] [--iters 3000]

The same as `coin-cl train`, written against the Python API so you can change what you need.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import coin_cl
from coin_cl.gs.model_kinds import scaled_model_config
from coin_cl.gs.trainer import TrainConfig, make_trainer
from coin_cl.scene.splits import split_indices


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--model", choices=("scaffold", "3dgs"), default="scaffold")
    ap.add_argument("--iters", type=int, default=3000)
    ap.add_argument("--resolution", type=float, default=1.0)
    ap.add_argument("--holdout", type=int, default=8, help="every k-th view is held out")
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    scene = coin_cl.load_scene(args.scene)  # a plain COLMAP folder: every view is a training view
    scene = scene.resized(args.resolution)
    train, held_out = split_indices(scene, args.holdout)
    cfg = TrainConfig(model=args.model, iters=args.iters, ckpt_every=max(1, args.iters // 4))
    model_cfg = scaled_model_config(args.model, args.iters)
    trainer = make_trainer(scene, train, held_out, cfg, args.out, model_cfg=model_cfg, device=args.device)
    result = trainer.train()
    print(
        f"{result['step']} steps; held-out PSNR {result.get('psnr', float('nan')):.2f} dB; wrote {args.out}/"
    )
    return result


if __name__ == "__main__":
    main()
