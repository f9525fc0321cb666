"""The ghost figure of a removal: the share of mask pixels in the object-absent test views
whose rendered depth lies more than 10 % in front of a reference depth (`metrics.ghost_fraction`).

Reference depth: the truth on synthetic scenes; on SPIn-NeRF a Scaffold-GS fitted to the 5
object-absent ground-truth views (cached under --out). Used by benchmarks/coin.py's rows and runnable
alone on run folders:

    python benchmarks/ghost.py RUN_DIR [RUN_DIR ...] [--data ../shared/data/spinnerf_scene1] [--iters 600]
        [--grid docs/img/NAME.png [--views 0,2]]

--grid writes, per test view (rows), each run's render and depth on the mask's bounding box, then the
reference depth and the truth (columns); depth is shown as disparity on one scale per row, the mask's
outline in red. The runs' final models are rendered (eval renders are not needed).

Last line JSON: {run: ghost} with the reference's fit figures.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, default_data, git_commit  # noqa: E402

from coin_cl.metrics import ghost_fraction  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402


def reference_depths(scene, out: Path, iters: int = 600) -> dict[int, np.ndarray]:
    """{test view: depth [H, W]} from a Scaffold-GS fitted to the object-absent test views (cached in
    `out/depths.npz`; NaN where its alpha < 0.5)."""
    cache = out / "depths.npz"
    if cache.is_file():
        z = np.load(cache)
        return {int(k): z[k] for k in z.files}
    from coin_cl.pipeline.refgs import fit_captured

    test = list(scene.test_idx)
    tr = fit_captured(scene, test, "scaffold", iters, 0, "opencl", None, out / "gs")
    depths = {}
    for i in test:
        with torch.no_grad():
            r = tr.model.render(scene.cameras[i], tr.step, return_depth=True)
        d = r.depth.numpy().astype(np.float64)
        d[r.alpha.numpy() < 0.5] = np.nan
        depths[i] = d
    out.mkdir(parents=True, exist_ok=True)
    np.savez(cache, **{str(k): v for k, v in depths.items()})
    return depths


def ghost_of_model(model, scene, depths: dict[int, np.ndarray]) -> float:
    """Mean ghost figure of `model` over the test views with a mask."""
    vals = []
    for i, ref in depths.items():
        m = np.asarray(scene.masks[i], bool)
        if not m.any():
            continue
        with torch.no_grad():
            r = model.render(scene.cameras[i], 10**9, return_depth=True)
        d = r.depth.numpy().astype(np.float64)
        d[r.alpha.numpy() < 0.5] = np.inf  # nothing drawn there: no ghost
        vals.append(ghost_fraction(d, ref, m))
    return float(np.nanmean(vals)) if vals else float("nan")


def final_model(run: Path):
    """The final model of a `coin-cl run` folder (the stage eval scored; the last stage that trained
    one when the folder has no eval)."""
    from coin_cl.checkpoint import load_checkpoint
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME

    manifest = run / "eval" / "manifest.json"
    if manifest.is_file():
        folder = run / json.loads(manifest.read_text())["settings"]["final"]
    else:
        folder = next(run / s for s in ("4_ted", "2_refgs") if any((run / s).rglob(CKPT_NAME)))
    ckpt = sorted(folder.rglob(CKPT_NAME), key=lambda p: p.stat().st_mtime)[-1]
    return model_from_state(load_checkpoint(ckpt)["model"])


def ghost_of_run(run: Path, scene, depths: dict[int, np.ndarray]) -> float:
    """The ghost figure of a `coin-cl run` folder's final model."""
    return ghost_of_model(final_model(run), scene, depths)


def depth_grid(runs: list[Path], scene, depths: dict[int, np.ndarray], views: list[int], cell: int = 160):
    """[rows, cols, 3] uint8: per test view, each run's render and depth, the reference depth and the
    truth on the mask's bounding box (+8 px); disparity on one scale per row; mask outline in red."""
    import cv2

    from coin_cl.metrics import bbox_crop

    models = [final_model(r) for r in runs]
    rows = []
    for i in views:
        m = np.asarray(scene.masks[i], bool)
        crop = bbox_crop(m, pad=8)
        ref = depths[i]
        tiles, disp = [], []
        for model in models:
            with torch.no_grad():
                r = model.render(scene.cameras[i], 10**9, return_depth=True)
            d = r.depth.numpy().astype(np.float64)
            d[r.alpha.numpy() < 0.5] = np.nan
            tiles.append(r.image.clamp(0, 1).numpy())
            disp.append(1.0 / d)
            tiles.append(None)
        disp.append(1.0 / ref)
        lo, hi = np.nanpercentile(np.concatenate([x[crop].ravel() for x in disp]), [1, 99])
        scaled = [np.clip((np.nan_to_num(x, nan=lo) - lo) / (hi - lo + 1e-12), 0, 1) for x in disp]
        as_rgb = [np.repeat(x[..., None], 3, 2) for x in scaled]
        tiles = [t if t is not None else as_rgb[k // 2] for k, t in enumerate(tiles)]
        tiles += [as_rgb[-1], np.asarray(scene.images[i], np.float32)]
        edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        out = []
        for t in tiles:
            t = np.array(t[..., :3], np.float32)
            t[edge] = (1.0, 0.0, 0.0)
            t = t[crop]
            h, w = t.shape[:2]
            sc = cell / max(h, w)
            t = cv2.resize(t, (max(1, round(w * sc)), max(1, round(h * sc))), interpolation=cv2.INTER_AREA)
            out.append(
                np.pad(t, ((0, cell + 4 - t.shape[0]), (0, cell + 4 - t.shape[1]), (0, 0)), constant_values=1)
            )
        rows.append(np.concatenate(out, 1))
    return (np.concatenate(rows, 0) * 255).round().astype(np.uint8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--iters", type=int, default=600, help="steps of the reference GS on the test views")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "out" / "ghost_reference")
    ap.add_argument("--grid", type=Path, default=None, help="write the render/depth grid here (PNG)")
    ap.add_argument(
        "--views", default=None, help="test views of the grid (positions in test_idx; default all)"
    )
    args = ap.parse_args()
    scene = load_scene(args.data, resolution=args.resolution)
    depths = reference_depths(scene, args.out / f"r{args.resolution:g}_i{args.iters}", args.iters)
    print(f"ghost figure; CPU {cpu_model()}; commit {git_commit()}; reference: Scaffold-GS, {args.iters} "
          f"steps on the {len(depths)} object-absent views at resolution {args.resolution}")  # fmt: skip
    res = {}
    print("| run | ghost (share of mask px > 10 % in front) |\n|---|---|")
    for run in args.runs:
        res[str(run)] = ghost_of_run(run, scene, depths)
        print(f"| {run} | {res[str(run)]:.3f} |")
    if args.grid is not None:
        from coin_cl.scene.io import write_png

        test = [i for i in depths if np.asarray(scene.masks[i]).any()]
        views = test if args.views is None else [test[int(k)] for k in args.views.split(",")]
        write_png(args.grid, depth_grid(args.runs, scene, depths, views) / 255.0)
        print(
            f"grid: {args.grid} (columns: "
            + ", ".join(f"{r.name} render, {r.name} depth" for r in args.runs)
            + ", reference depth, truth)"
        )
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
