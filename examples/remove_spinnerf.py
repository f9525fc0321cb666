"""Remove the box from the shared SPIn-NeRF scene with CoIn and score it against the ground truth.

    python examples/remove_spinnerf.py [--data ../shared/data/spinnerf_scene1] [--budget 10]
        [--out runs/spinnerf] [--iters N] [--prior-sampler [--prior-seconds S --clg-steps N]]

Uses the dataset's LaMa inpaints as the initial 2D results (seg masks); CLG propagates the reference
without a sampler (the default: the embedded scene prior's sampler did not pay for its minutes here),
or with `--prior-sampler` samples with the scene prior and the analytic features (no weights
needed); pass --sd-path / --dino-path for the paper's models.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import coin_cl
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig


def default_data() -> Path:
    env = os.environ.get("COIN_DATA")
    base = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return base / "spinnerf_scene1"


def main(argv: list[str] | None = None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--out", type=Path, default=Path("runs/spinnerf"))
    ap.add_argument("--budget", type=float, default=10.0, help="training minutes to aim at")
    ap.add_argument("--resolution", type=float, default=None, help="default: from the image size (0.5 here)")
    ap.add_argument("--sd-path", default=None)
    ap.add_argument("--dino-path", default=None)
    ap.add_argument("--iters", type=int, default=None, help="explicit iterations per training stage")
    ap.add_argument("--prior-sampler", action="store_true", help="CLG samples with the embedded scene prior")
    ap.add_argument("--prior-seconds", type=float, default=None, help="scene prior training (smoke runs)")
    ap.add_argument("--clg-steps", type=int, default=None, help="CLG's DDIM steps (default: the model's)")
    args = ap.parse_args(argv)

    scene = coin_cl.load_scene(args.data)
    cfg = CoInConfig(resolution=args.resolution, sd_path=args.sd_path, dino_path=args.dino_path,
                     prior_seconds=args.prior_seconds,
                     clg=CLGConfig(steps=args.clg_steps, prior_sampler=args.prior_sampler))  # fmt: skip
    cfg = cfg.with_iters(args.iters)
    result = coin_cl.inpaint(scene, args.out, mask_kind="seg", budget=args.budget, config=cfg)
    if result.metrics:
        m = result.metrics
        print(f"PSNR {m['psnr']:.2f}  m-PSNR {m['m_psnr']:.2f}  HF ratio {m['hf_ratio']:.2f}  "
              f"bbox GMSD {m['bbox_gmsd']:.3f}")  # fmt: skip
    print(f"final Gaussians: {result.ply}; renders: {result.renders}; log: {args.out}/log.json")
    return result


if __name__ == "__main__":
    main()
