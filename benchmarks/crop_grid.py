"""A crop grid of the masked region of every ground-truth test view: one column per run folder (its
eval render), then the truth; rows are test views. Scores hide what an eye sees at once (the HF ratio
counts noise as texture), so every results table has one of these beside it. A folder without
`eval/renders` is read from its `pred/` (the demo's masked-reconstruction row).

    python benchmarks/crop_grid.py RUN_DIR [RUN_DIR ...] --out docs/img/NAME.png [--cell 160]
        [--views 0 2 4] [--transpose] [--capture SCENE]

The crop is the mask's bounding box plus 8 px (`coin_cl.metrics.bbox_crop`); the scene (masks, truth)
comes from the first run's `0_scene/scene`. With `--capture SCENE` (the scene folder the runs were
made from) the grid is drawn at the photos' size instead: each run's renders at that size
(`eval/capture/renders`, which eval writes for a run below it, else `eval/renders` of a run at it),
so runs at different working sizes sit side by side. Prints the column order.
"""

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from coin_cl import metrics
from coin_cl.scene import load_scene
from coin_cl.scene.io import read_image, to_uint8, view_stem, write_png


def tile_row(tiles: list[np.ndarray], cell: int) -> np.ndarray:
    """Equal-size crops [h, w, 3] float -> one row [cell + 4, n * (cell + 4), 3]: each scaled so its
    longer side is `cell` (area), padded white."""
    h, w = tiles[0].shape[:2]
    sc = cell / max(h, w)
    size = (max(1, round(w * sc)), max(1, round(h * sc)))
    tiles = [cv2.resize(t, size, interpolation=cv2.INTER_AREA) for t in tiles]
    pad = [((0, cell + 4 - t.shape[0]), (0, cell + 4 - t.shape[1]), (0, 0)) for t in tiles]
    return np.concatenate([np.pad(t, p, constant_values=1) for t, p in zip(tiles, pad)], axis=1)


def grid(
    runs: list[Path],
    cell: int = 160,
    views: list[int] | None = None,
    transpose: bool = False,
    capture: Path | None = None,
) -> np.ndarray:
    """[rows * (cell + 4), (len(runs) + 1) * (cell + 4), 3] uint8; `views`: positions among the
    masked test views to keep (default all); `transpose`: one row per run (then the truth), one
    column per view; `capture`: the runs' scene folder, to draw at its photos' size (module doc)."""
    scene = load_scene(capture if capture is not None else runs[0] / "0_scene" / "scene")
    rows = []
    masked = [i for i in scene.test_idx if np.asarray(scene.masks[i], bool).any()]
    for i in masked if views is None else [masked[v] for v in views]:
        mask = np.asarray(scene.masks[i], bool)
        if not mask.any():
            continue
        crop = metrics.bbox_crop(mask, pad=8)
        stem = view_stem(scene.cameras[i].name, i)
        tiles = []
        for r in runs:
            path = render_of(r, stem, at_capture=capture is not None)
            img = read_image(path)
            if img.shape[:2] != mask.shape:
                fix = (
                    "a run below the photos' size needs eval's renders at it (eval/capture/renders)"
                    if capture is not None
                    else "runs at different working sizes meet at the photos' size: pass --capture SCENE"
                )
                raise ValueError(
                    f"{path} is {img.shape[1]}x{img.shape[0]} where view {stem} is "
                    f"{mask.shape[1]}x{mask.shape[0]}: {fix}"
                )
            tiles.append(img[crop])
        tiles.append(np.asarray(scene.images[i], np.float32)[crop])
        rows.append(tile_row(tiles, cell))
    if not rows:
        raise ValueError(f"{runs[0]} has no ground-truth test view with a mask")
    out = np.concatenate(rows, axis=0)
    if transpose:  # cut into cells and lay them out the other way round
        c = cell + 4
        cells = out.reshape(len(rows), c, len(runs) + 1, c, 3).transpose(2, 0, 1, 3, 4)
        out = cells.transpose(0, 2, 1, 3, 4).reshape((len(runs) + 1) * c, len(rows) * c, 3)
    return to_uint8(out)


def render_dir(run: Path, at_capture: bool = False) -> Path:
    """A run's test-view renders: a CoIn run's `eval/renders` (with `at_capture`, its
    `eval/capture/renders` where eval wrote them), or `pred/` of the demo's masked-reconstruction row
    (`coin_cl.demo.room_baseline`)."""
    if at_capture and (run / "eval" / "capture" / "renders").is_dir():
        return run / "eval" / "capture" / "renders"
    return run / "eval" / "renders" if (run / "eval" / "renders").is_dir() else run / "pred"


def render_of(run: Path, stem: str, at_capture: bool = False) -> Path:
    """The render of test view `stem` in `run` (`render_dir`), whatever its extension (masked
    reconstruction names its renders after the camera, e.g. a capture's .jpg)."""
    d = render_dir(run, at_capture)
    found = [d / f"{stem}.png"] if (d / f"{stem}.png").is_file() else sorted(d.glob(f"{stem}.*"))
    if not found:
        raise FileNotFoundError(f"{d} has no render of test view {stem}")
    return found[0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cell", type=int, default=160)
    ap.add_argument(
        "--views",
        type=int,
        nargs="+",
        default=None,
        help="positions among the masked test views to show (default: every one)",
    )
    ap.add_argument("--transpose", action="store_true", help="one row per run, one column per view")
    ap.add_argument(
        "--capture",
        type=Path,
        default=None,
        help="the runs' scene folder: draw at its photos' size (runs at any working size)",
    )
    args = ap.parse_args()
    write_png(args.out, grid(args.runs, args.cell, args.views, args.transpose, args.capture))
    what = "rows" if args.transpose else "columns"
    print(f"{what}:", " | ".join(r.name for r in args.runs), "| truth;", f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
