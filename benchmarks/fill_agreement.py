"""Benchmark: where the views disagree about the hole (`coin_cl.agreement` on a finished run).

For a `coin-cl run` folder, every training view's region (the part of its mask stage 1 filled:
`0_refine/unseen` for a refined run, else the mask) is carried into its two nearest views through
Ref-GS's depth of each view (`2_refgs/depths`, the coarse model CoIn's later stages stand on), and
compared there. Rows:

- stage-1 fills (`1_inpaint/images`): the per-view inpaints, each made on its own;
- CLG's images (`3_clg/images`, stage 1's where CLG kept the input), when CLG ran;
- the final model's renders of the training views (rendered here): one 3D answer seen from each
  view, so what they disagree by is the ruler's floor (depth error, view-dependent colour);
- the final render against each view's own fill, inside its region: how far the 3D fit moved
  from what each view's fill said.

    python benchmarks/fill_agreement.py RUN [RUN ...] [--out DIR] [--crops N]

Prints a table per run (disagreement = mean |a - b| RGB in [0, 1] over the compared pixels;
coverage = share of the regions compared; seconds = this benchmark's time for the row), the CPU,
OpenCL device and commit, and with --out a crop grid per run (`DIR/<run name>_agreement.png`):
for the N pairs with the most compared pixels, one row each: view j's fill | view i's fill carried
into j | their difference (x4) | CLG's image of j | the final render of j.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_model, git_commit  # noqa: E402
from crop_grid import tile_row  # noqa: E402

from coin_cl.agreement import carried, cross_view_agreement, neighbour_pairs  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402
from coin_cl.scene.io import read_image, to_uint8, view_stem, write_png  # noqa: E402
from coin_cl.scene.masks import read_mask  # noqa: E402


def run_inputs(run: Path, render_dir: Path) -> dict:
    """The run's training cameras, regions, Ref-GS depths and the rows' images (module doc)."""
    from coin_cl.render_utils import render_checkpoint

    scene = load_scene(run / "0_scene" / "scene")
    train = [i for i in scene.train_idx if np.asarray(scene.masks[i], bool).any()]
    stems = [view_stem(scene.cameras[i].name, i) for i in train]
    unseen = run / "0_refine" / "unseen"
    regions = [
        read_mask(unseen / f"{s}.png")
        if (unseen / f"{s}.png").is_file()
        else np.asarray(scene.masks[i], bool)
        for s, i in zip(stems, train, strict=True)
    ]
    depths = [np.load(run / "2_refgs" / "depths" / f"{s}.npy") for s in stems]
    fills = [read_image(run / "1_inpaint" / "images" / f"{s}.png") for s in stems]
    clg = None
    if (run / "3_clg" / "images").is_dir():
        clg = [
            read_image(p) if (p := run / "3_clg" / "images" / f"{s}.png").is_file() else f
            for s, f in zip(stems, fills, strict=True)
        ]
    render_checkpoint(run, "train", dest=render_dir)
    renders = [read_image(render_dir / "train" / f"{s}.png") for s in stems]
    return {"cams": [scene.cameras[i] for i in train], "stems": stems, "regions": regions, "depths": depths,
            "fills": fills, "clg": clg, "renders": renders}  # fmt: skip


def in_region_distance(a: list[np.ndarray], b: list[np.ndarray], regions: list[np.ndarray]) -> float:
    """Mean |a - b| RGB over every view's region (pixel-weighted)."""
    num = sum(float(np.abs(x[r] - y[r]).sum()) / 3 for x, y, r in zip(a, b, regions, strict=True))
    return num / max(1, sum(int(r.sum()) for r in regions))


def crop_grid(inp: dict, pairs: list, n: int, cell: int = 128) -> np.ndarray:
    from coin_cl import metrics

    rows = []
    for p in sorted((p for p in pairs if p.pixels), key=lambda p: -p.pixels)[:n]:
        j, i = p.dst, p.src
        warped, valid = carried(inp["cams"][j], inp["cams"][i], inp["fills"][i], inp["regions"][j],
                                inp["regions"][i], inp["depths"][j], inp["depths"][i])  # fmt: skip
        crop = metrics.bbox_crop(inp["regions"][j], pad=8)
        fill = np.asarray(inp["fills"][j], np.float64)
        diff = np.where(valid[..., None], np.clip(4 * np.abs(fill - warped), 0, 1), 0.0)
        shown = np.where(valid[..., None], warped, 0.5 * fill)  # not carried: the view's own fill, dimmed
        clg = inp["clg"][j] if inp["clg"] is not None else fill
        rows.append(tile_row([fill[crop], shown[crop], diff[crop], np.asarray(clg)[crop],
                              np.asarray(inp["renders"][j])[crop]], cell))  # fmt: skip
    return to_uint8(np.concatenate(rows, 0)) if rows else np.zeros((1, 1, 3), np.uint8)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="finished coin-cl run folders")
    ap.add_argument("--out", type=Path, default=None,
                    help="crop grids and renders (default: no grid, renders in a temp folder)")  # fmt: skip
    ap.add_argument("--crops", type=int, default=4, help="pairs shown in each crop grid")
    args = ap.parse_args(argv)
    from coin_cl.engine.runtime import get_runtime

    print(f"# fill agreement: CPU {cpu_model()}, OpenCL {get_runtime().name}, commit {git_commit()}")
    result = {}
    for run in args.runs:
        tag = run.name
        t0 = time.time()
        # the training views' renders: under --out, else in a temporary folder (never in the run's)
        with tempfile.TemporaryDirectory(prefix="fill-agreement-") as tmp:
            inp = run_inputs(run, (args.out or Path(tmp)) / f"{tag}_renders")
        t_load = time.time() - t0
        pairs = neighbour_pairs(inp["cams"])
        print(f"\n{run}: {len(inp['cams'])} masked training views, {len(pairs)} neighbour pairs "
              f"(inputs and renders {t_load:.1f} s)")  # fmt: skip
        print("| row | disagreement | coverage | pixels | seconds |")
        print("|---|---|---|---|---|")
        rows = {"stage-1 fills": inp["fills"], "CLG images": inp["clg"], "final renders": inp["renders"]}
        per_pair = None
        for name, imgs in rows.items():
            if imgs is None:
                print(f"| {name} | (stage left out) | | | |")
                continue
            t = time.time()
            pp, s = cross_view_agreement(inp["cams"], imgs, inp["regions"], inp["depths"], pairs)
            per_pair = pp if name == "stage-1 fills" else per_pair
            print(f"| {name} | {s['disagreement']:.4f} | {s['coverage']:.2f} | {s['pixels']} | "
                  f"{time.time() - t:.2f} |")  # fmt: skip
            result[f"{tag}_{name.split()[0].lower()}_disagreement"] = s["disagreement"]
        t = time.time()
        as64 = [[np.asarray(x, np.float64) for x in inp[k]] for k in ("renders", "fills")]
        moved = in_region_distance(*as64, inp["regions"])
        print(f"| final render vs each view's fill (in its region) | {moved:.4f} | 1.00 | "
              f"{sum(int(r.sum()) for r in inp['regions'])} | {time.time() - t:.2f} |")  # fmt: skip
        result[f"{tag}_render_vs_fill"] = moved
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            path = args.out / f"{tag}_agreement.png"
            write_png(path, crop_grid(inp, per_pair, args.crops))
            print(f"crops: {path} (columns: view j's fill | view i's fill carried into j | difference x4 | "
                  "CLG's image of j | the final render of j)")  # fmt: skip
    print(json.dumps({**result, "cpu": cpu_model(), "commit": git_commit()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
