"""The ghost figure of a removal (issue 21): the share of mask pixels in the object-absent test views
whose rendered depth lies more than 10 % in front of a reference depth (`metrics.ghost_fraction`).

Reference depth: the truth on synthetic scenes; on SPIn-NeRF a Scaffold-GS fitted to the 5
object-absent ground-truth views (cached under --out). Used by benchmarks/coin.py's rows and runnable
alone on run folders:

    python benchmarks/ghost.py RUN_DIR [RUN_DIR ...] [--data ../shared/data/spinnerf_scene1] [--iters 600]

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


def ghost_of_run(run: Path, scene, depths: dict[int, np.ndarray]) -> float:
    """The ghost figure of a `coin-cl run` folder's final model."""
    from coin_cl.gs.trainer import CKPT_NAME, model_from_state

    final = json.loads((run / "eval" / "manifest.json").read_text())["settings"]["final"]
    ckpt = sorted((run / final).rglob(CKPT_NAME), key=lambda p: p.stat().st_mtime)[-1]
    model = model_from_state(torch.load(ckpt, weights_only=False)["model"])
    return ghost_of_model(model, scene, depths)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--iters", type=int, default=600, help="steps of the reference GS on the test views")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "out" / "ghost_reference")
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
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
