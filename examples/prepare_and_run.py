"""From a folder of photos to the object removed: `coin-cl prepare` then `coin-cl run`, in Python.

    python examples/prepare_and_run.py --photos my_photos --box IMG_0012.jpg 850 400 1400 900 \
        --out runs/mine --budget 20

Without --photos it renders a tiny capture of the synthetic room (12 photos, the object's box
known) so the example runs anywhere. Without --budget or --iters it stops after preparation and
prints the `coin-cl run` command (the run is the long part). What it writes: OUT/scene (images/,
sparse/0, masks/, prepare_report.txt, masks_contact_sheet.png) and, with a run, OUT/run.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from coin_cl.prepare import Annotation, SfmConfig, prepare


def synthetic_photos(folder: Path) -> tuple[str, list[int]]:
    """Photos of the synthetic room (12 cameras on a 90 degree arc, 256x192) into `folder`; returns
    the photo where the object is largest and its box (x0, y0, x1, y1) from the true mask."""
    from coin_cl.prepare.capture import synthetic_capture
    from coin_cl.scene.masks import bbox

    cap = synthetic_capture(folder)
    k = int(np.argmax([m.sum() for m in cap.masks]))
    y0, y1, x0, x1 = bbox(cap.masks[k])
    return cap.photos[k].name, [x0 - 3, y0 - 3, x1 + 3, y1 + 3]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", type=Path, default=None, help="your photos (default: a synthetic capture)")
    ap.add_argument("--box", nargs=5, default=None, metavar=("VIEW", "X0", "Y0", "X1", "Y1"),
                    help="the object's box in one photo, in its pixels")  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path("runs/prepare_example"))
    ap.add_argument("--width", type=int, default=1008, help="working width of the prepared images")
    ap.add_argument("--budget", type=float, default=None, help="minutes for `coin-cl run` (default: no run)")
    ap.add_argument("--iters", type=int, default=None, help="explicit iterations per training stage")
    args = ap.parse_args(argv)

    photos = args.photos
    if photos is None:
        photos = args.out / "photos"
        photos.mkdir(parents=True, exist_ok=True)
        view, box = synthetic_photos(photos)
    elif args.box is None:
        raise SystemExit("give --box VIEW X0 Y0 X1 Y1 with your photos")
    if args.box is not None:
        view, box = args.box[0], [float(v) for v in args.box[1:]]
    scene_dir = args.out / "scene"
    report, masks = prepare(
        photos, scene_dir, Annotation(view=view, box=tuple(box)), sfm=SfmConfig(width=args.width)
    )
    print(report.text(), end="")
    print(
        f"masks: {scene_dir / 'masks'}; look at {scene_dir / 'masks_contact_sheet.png'} and fix any by hand"
    )
    out = {"scene": scene_dir, "registered": len(report.registered), "masks": masks}
    if args.budget is None and args.iters is None:
        print(f"next: coin-cl run {scene_dir} --out {args.out / 'run'} --budget 20")
        return out
    import coin_cl
    from coin_cl.pipeline.coin import CoInConfig

    cfg = CoInConfig().with_iters(args.iters)
    result = coin_cl.inpaint(coin_cl.load_scene(scene_dir), args.out / "run", budget=args.budget, config=cfg)
    print(f"final Gaussians: {result.ply}")
    out["run"] = result
    return out


if __name__ == "__main__":
    main()
