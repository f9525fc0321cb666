"""Where the rooms' m-PSNR is decided: the test masks of a synthetic room cut into pixel
classes by the exact visibility from the training views (`rooms.observed_from`) and by the split a
CoIn run found (its stage 0_refine's `unseen/`), each run's PSNR and share of the squared error on
each class, beside reference fills of the exactly unseen pixels (black, the mean colour of a ring
around the mask, the oracle mean colour of the unseen pixels themselves) and, for a masked-
reconstruction run (`train/` checkpoint), its opacity there; for every run its lightness there and
its ghost figure on them (share rendered more than 10 % in front of the exact depth); then where each
run's bbox GMSD is decided: the GMS map of the mask's bounding box (GMSD is its standard deviation)
cut into the pixels outside the mask and the exactly observed and unseen ones. Ends with a crop grid of
every test view: the exact split (green observed by some training view, red unseen by all), each
run's render, the truth.

    python benchmarks/room_unseen.py --scene room360 --split RUN/coin \
        coin=RUN/coin masked_recon=RUN/masked_recon --grid docs/img/room360_unseen_crops.png

A run is a CoIn folder (renders in eval/renders/) or a masked-reconstruction folder (pred/); the
scene is rebuilt from `rooms.SCENES` at the benchmark's default size. Scores only, no timing: the
runs' minutes are in `benchmarks/rooms.py`'s table. Last line JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
from common import cpu_model, git_commit
from rooms import SCENES, observed_from

from coin_cl.evaluation import split_tile
from coin_cl.metrics import bbox_crop, ghost_fraction, gmsd_map
from coin_cl.scene.io import read_image, to_uint8, write_png
from coin_cl.scene.masks import read_mask

CLASSES = (
    "observed, found observed",
    "observed, found unseen",
    "unseen, found unseen",
    "unseen, found observed",
)
RING_PX = 4  # the ring around the mask whose mean colour is the "ring mean" fill
GMS_CLASSES = ("outside the mask", "observed", "unseen")


def gms_by_class(pred: np.ndarray, gt: np.ndarray, classes: list[np.ndarray]) -> tuple[float, list, list]:
    """(bbox GMSD, [mean GMS], [share of the GMS map's variance]) of one view, each list over
    `classes` ((H, W) bool, disjoint, covering the mask's bounding box); a class is resized to the
    map's half resolution (a map pixel belongs to the class that covers most of it)."""
    crop = bbox_crop(classes[1] | classes[2])
    v, q = gmsd_map(pred[crop], gt[crop])
    dev = (q - q.mean()) ** 2
    means, shares = [], []
    for c in classes:
        c = cv2.resize(c[crop].astype(np.float32), q.shape[::-1], interpolation=cv2.INTER_AREA) > 0.5
        means.append(float(q[c].mean()) if c.any() else float("nan"))
        shares.append(float(dev[c].sum() / max(dev.sum(), 1e-12)))
    return v, means, shares


def _render(run: Path, name: str) -> np.ndarray:
    for p in (run / "eval" / "renders" / name, run / "pred" / name):
        if p.is_file():
            return read_image(p)
    raise FileNotFoundError(f"{run} has no render of {name} (eval/renders/ or pred/)")


def _psnr(se: float, n: int) -> float:
    return float(10 * np.log10(3 * n / se)) if n and se > 0 else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=FOLDER")
    ap.add_argument("--scene", choices=list(SCENES), required=True)
    ap.add_argument("--split", type=Path, required=True, help="the CoIn run whose 0_refine split is used")
    ap.add_argument("--grid", type=Path, default=None, help="write the crop grid here")
    ap.add_argument("--size", type=int, nargs=2, default=(192, 144))
    ap.add_argument("--views", type=int, default=24)
    args = ap.parse_args()
    runs = dict(a.split("=", 1) for a in args.runs)
    from coin_cl.scene.synthetic import make_synthetic

    syn = make_synthetic(coverage=SCENES[args.scene], n_views=args.views, width=args.size[0],
                         height=args.size[1], seed=0)  # fmt: skip
    train = [j for j, t in enumerate(syn.is_test) if not t]
    tests = [j for j, t in enumerate(syn.is_test) if t]
    ring_k = np.ones((2 * RING_PX + 1,) * 2, np.uint8)
    se = {k: {c: 0.0 for c in CLASSES} for k in runs}
    count = dict.fromkeys(CLASSES, 0)
    fills = {k: [] for k in ("black", "ring mean", "oracle mean", *runs)}  # per-view PSNR on the unseen part
    light = {k: [] for k in ("truth", *runs)}
    ghost = {k: [] for k in runs}
    alpha: dict[str, list] = {}
    gms: dict[str, list] = {k: [] for k in runs}  # per view: (GMSD, means, shares)
    rows = []
    for n in tests:
        m, t = syn.masks[n], syn.absent[n]
        obs = observed_from(syn, n, train)
        uns = m & ~obs
        found = read_mask(args.split / "0_refine" / "unseen" / syn.cameras[n].name, m.shape)
        cls = dict(zip(CLASSES, (obs & ~found, obs & found, uns & found, uns & ~found), strict=True))
        for c, px in cls.items():
            count[c] += int(px.sum())
        ring = cv2.dilate(m.astype(np.uint8), ring_k).astype(bool) & ~m
        ref = {"black": np.zeros_like(t), "ring mean": np.broadcast_to(t[ring].mean(0), t.shape),
               "oracle mean": np.broadcast_to(t[uns].mean(0), t.shape)}  # fmt: skip
        preds = {k: _render(Path(d), syn.cameras[n].name) for k, d in runs.items()}
        for k, f in {**ref, **preds}.items():
            fills[k].append(_psnr(float(((f[uns] - t[uns]) ** 2).sum()), int(uns.sum())))
        light["truth"].append(float(t[uns].mean()))
        for k, p in preds.items():
            err = ((p - t) ** 2).sum(-1)
            for c, px in cls.items():
                se[k][c] += float(err[px].sum())
            light[k].append(float(p[uns].mean()))
            gms[k].append(gms_by_class(p, t, [~m, obs, uns]))
            a, d = _alpha_depth(Path(runs[k]), syn.cameras[n])
            if a is not None:  # masked reconstruction: how opaque it is where nobody saw
                alpha.setdefault(k, []).append(a[uns])
            if d is not None:
                ghost[k].append(ghost_fraction(d, syn.depth_absent[n], uns))
        if args.grid is not None:
            ys, xs = np.nonzero(m)
            y0, y1 = max(0, ys.min() - 6), min(m.shape[0], ys.max() + 7)
            x0, x1 = max(0, xs.min() - 6), min(m.shape[1], xs.max() + 7)
            tiles = [split_tile(obs, uns)] + list(preds.values()) + [t]
            tiles = [cv2.resize(np.ascontiguousarray(x[y0:y1, x0:x1]), (96, 96),
                                interpolation=cv2.INTER_NEAREST) for x in tiles]  # fmt: skip
            gap = np.ones((96, 3, 3), np.float32)
            rows.append(np.concatenate([x for tile in tiles for x in (tile, gap)][:-1], axis=1))

    total = sum(count.values())
    print(f"# {args.scene}: {len(tests)} test views, {total} mask px; CPU {cpu_model()}, "
          f"commit {git_commit()}")  # fmt: skip
    print(f"\nPixel classes (exact visibility, the split of {args.split}): PSNR over the class's "
          "pixels / share of the run's squared error in the mask")  # fmt: skip
    print("| class | share of the masks | " + " | ".join(runs) + " |")
    print("|---" * (len(runs) + 2) + "|")
    for c in CLASSES:
        cells = [f"{_psnr(se[k][c], count[c]):.2f} / {se[k][c] / max(sum(se[k].values()), 1e-12):.2f}"
                 for k in runs]  # fmt: skip
        print(f"| {c} | {count[c] / max(total, 1):.2f} | " + " | ".join(cells) + " |")
    print("\nThe exactly unseen pixels: PSNR (mean over test views), mean lightness (truth "
          f"{np.mean(light['truth']):.3f})")  # fmt: skip
    print("| fill | PSNR | lightness | ghost | opacity (alpha < 0.5 share) |")
    print("|---|---|---|---|---|")
    for k, v in fills.items():
        lt = f"{np.mean(light[k]):.3f}" if k in light else "-"
        gh = f"{np.nanmean(ghost[k]):.2f}" if ghost.get(k) else "-"
        a = np.concatenate(alpha[k]) if k in alpha else None
        op = f"{a.mean():.2f} ({(a < 0.5).mean():.2f})" if a is not None else "-"
        print(f"| {k} | {np.nanmean(v):.2f} | {lt} | {gh} | {op} |")
    print(
        "\nWhere bbox GMSD (luminance) is decided: the GMS map of each view's box, by exact class: mean "
        "GMS (1: gradient magnitudes agree) / share of the map's variance (means over test views)"
    )
    print("| run | bbox GMSD | " + " | ".join(GMS_CLASSES) + " |")
    print("|---" * (len(GMS_CLASSES) + 2) + "|")
    for k, per_view in gms.items():
        g = np.nanmean([v for v, _, _ in per_view])
        mean = np.nanmean([m_ for _, m_, _ in per_view], axis=0)
        share = np.nanmean([s_ for _, _, s_ in per_view], axis=0)
        cells = [f"{a:.3f} / {b:.2f}" for a, b in zip(mean, share, strict=True)]
        print(f"| {k} | {g:.3f} | " + " | ".join(cells) + " |")
    if args.grid is not None:
        sep = np.ones((3, rows[0].shape[1], 3), np.float32)
        write_png(args.grid, to_uint8(np.concatenate([x for r in rows for x in (r, sep)][:-1], axis=0)))
        print(f"\ngrid: {args.grid} (rows: test views; columns: exact split, " + ", ".join(runs) + ", truth)")
    result = {
        "scene": args.scene,
        "unseen_psnr": {k: float(np.nanmean(v)) for k, v in fills.items()},
        "unseen_ghost": {k: float(np.nanmean(v)) for k, v in ghost.items() if v},
        "class_share": {c: count[c] / max(total, 1) for c in CLASSES},
        "class_psnr": {k: {c: _psnr(se[k][c], count[c]) for c in CLASSES} for k in runs},
        "bbox_gmsd": {k: float(np.nanmean([v for v, _, _ in g])) for k, g in gms.items()},
    }
    print(json.dumps(result))
    return 0


_MODELS: dict[Path, object] = {}


def _alpha_depth(run: Path, camera) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(opacity (H, W) or None, depth (H, W), NaN where alpha <= 0.5, or None) of `run` seen from
    `camera`: a CoIn run's eval/depths/ (no opacity), else the checkpoint under train/ (masked
    reconstruction), else neither."""
    p = run / "eval" / "depths" / (Path(camera.name).stem + ".npy")
    if p.is_file():
        return None, np.load(p)
    if not (run / "train").is_dir():
        return None, None
    import torch

    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.pipeline.stages import load_model

    folder = run / "train"
    if folder not in _MODELS:
        _MODELS[folder] = load_model(folder, CKPT_NAME, model_from_state)
    with torch.no_grad():
        r = _MODELS[folder].render(camera, 10**9, return_depth=True)
    a = r.alpha.numpy()
    return a, np.where(a > 0.5, r.depth.numpy(), np.nan)


if __name__ == "__main__":
    sys.exit(main())
