"""A crop grid of one test view of a synthetic room for the removal-geometry results:
row 1: the split of its mask (green observed by the training views, red the unseen core; from the
first run's stage 0_refine), then each run's render, then the truth; row 2: each run's rendered
depth where its eval wrote one (`eval/depths/`), then the exact depth (one TURBO scale, near =
blue). Masked-reconstruction folders (`pred/`, `train/`) are rendered from their checkpoint.

    python benchmarks/room_view_grid.py RUN [RUN ...] --view 2 --out docs/img/room_view2.png

Prints the column order."""

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from coin_cl import metrics
from coin_cl.evaluation import split_tile
from coin_cl.scene import load_scene
from coin_cl.scene.io import read_image, to_uint8, write_png
from coin_cl.scene.masks import read_mask


def _depth(run: Path, scene, i: int) -> np.ndarray | None:
    stem = Path(scene.cameras[i].name).stem
    p = run / "eval" / "depths" / f"{stem}.npy"
    if p.is_file():
        return np.load(p)
    # a run whose eval wrote no depth (older code): its final model; masked reconstruction: its 3DGS
    folder = next((run / f for f in ("4_ted", "2_refgs", "train") if (run / f).is_dir()), None)
    if folder is not None:
        import torch

        from coin_cl.gs.model_kinds import model_from_state
        from coin_cl.gs.trainer import CKPT_NAME
        from coin_cl.pipeline.stages import load_model

        model = load_model(folder, CKPT_NAME, model_from_state)
        with torch.no_grad():
            r = model.render(scene.cameras[i], 10**9, return_depth=True)
        return np.where(r.alpha.numpy() > 0.5, r.depth.numpy(), np.nan)
    return None


def _render(run: Path, scene, i: int) -> np.ndarray:
    name = scene.cameras[i].name
    for p in (run / "eval" / "renders" / name, run / "pred" / name):
        if p.is_file():
            return read_image(p)
    raise FileNotFoundError(f"{run} has no render of {name} (eval/renders/ or pred/)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--scene", type=Path, required=True, help="the room's scene folder (truth, exact depth)")
    ap.add_argument("--view", type=int, default=2, help="test view index (view_NNN)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", type=int, default=3)
    args = ap.parse_args()
    scene = load_scene(args.scene)
    i = [j for j in scene.test_idx if scene.cameras[j].name == f"view_{args.view:03d}.png"][0]
    m = np.asarray(scene.masks[i], bool)
    crop = metrics.bbox_crop(m, pad=8)
    stem = Path(scene.cameras[i].name).stem
    obs_p = args.runs[0] / "0_refine" / "observed" / f"{stem}.png"
    obs = read_mask(obs_p, m.shape) & m if obs_p.is_file() else np.zeros_like(m)
    ref = scene.extras["depth"][i]
    lo, hi = np.percentile(ref[m], (1, 99))

    def colour(d):
        t = np.clip((np.nan_to_num(d, nan=hi) - lo) / max(hi - lo, 1e-9), 0, 1)
        c = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1] / 255.0
        c[~np.isfinite(d)] = 0
        return c.astype(np.float32)

    top = [split_tile(obs, m & ~obs)] + [_render(r, scene, i) for r in args.runs] + [scene.images[i]]
    depths = [_depth(r, scene, i) for r in args.runs]
    bottom = [np.ones_like(top[0])] + [colour(d) if d is not None else np.ones_like(top[0]) for d in depths]
    bottom.append(colour(ref))
    s = args.scale

    def row(tiles):
        tiles = [cv2.resize(t[crop], None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST) for t in tiles]
        gap = np.ones((tiles[0].shape[0], 4, 3), np.float32)
        return np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)

    a, b = row(top), row(bottom)
    write_png(args.out, to_uint8(np.concatenate([a, np.ones((4, a.shape[1], 3), np.float32), b], axis=0)))
    print("columns: split (green observed, red unseen), " + ", ".join(str(r) for r in args.runs) + ", truth")
    print("rows: render; rendered depth (exact depth last), TURBO from", f"{lo:.2f} to {hi:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
