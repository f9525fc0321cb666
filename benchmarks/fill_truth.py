"""Benchmark: a run's 2D fills against the truth behind a virtual object, in the *training* views.

On a virtual-object scene (`coin-cl make-scene --from-capture`, docs/VIRTUAL_OBJECTS.md) the box is
painted into the training photos, so the capture's own photo is the truth behind it in every view,
not only in the test views. This scores what each 2D stage of a run handed on (stage 1's inpaints
I^_n in `1_inpaint/images`, CLG's images in `3_clg/images`), inside each training view's mask and
inside its unseen part (`0_refine/unseen`: what no capture shows, decided by the fill alone), against
the photo resized to the working size, and how far the views agree with the reference view: CLG's
recorded residual to the reference warped through P_k (`3_clg/views/*.json`, of the image it wrote).
Seconds: what the stage took (its manifest). One crop grid per run: per view, the mask's bounding
box of each stage's image, then the truth.

    python benchmarks/fill_truth.py RUN [RUN ...] [--capture ../shared/data/cup_capture] [--out DIR]

A run folder must come from a virtual-object scene of that capture (its views named after the
capture's photos). Prints a Markdown table; with --out writes fill_truth.md and <run>_crops.png.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import default_data  # noqa: E402

from coin_cl import metrics  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402
from coin_cl.scene.io import read_image, to_uint8, view_stem, write_png  # noqa: E402
from coin_cl.scene.masks import read_mask  # noqa: E402

STAGES = ("1_inpaint", "3_clg")


def truth_of(capture: Path, name: str, W: int, H: int) -> np.ndarray | None:
    """The capture's photo behind a view named after it (any extension), area-resized to W x H."""
    hits = sorted((capture / "images").glob(Path(name).stem + ".*"))
    if not hits:
        return None
    img = read_image(hits[0])
    return cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA) if img.shape[:2] != (H, W) else img


def stage_seconds(run: Path, stage: str) -> float | None:
    p = run / stage / "manifest.json"
    if not p.is_file():
        return None
    m = json.loads(p.read_text())
    return m.get("seconds") or m.get("seconds_when_run")


def score_run(run: Path, capture: Path, cell: int = 120) -> tuple[dict, np.ndarray | None]:
    """({stage: figures}, crop grid uint8 or None) of one run folder."""
    scene = load_scene(run / "0_scene" / "scene")
    per: dict[str, list[dict]] = {s: [] for s in STAGES}
    rows = []
    for i in scene.train_idx:
        mask = np.asarray(scene.masks[i], bool)
        if not mask.any():
            continue
        cam = scene.cameras[i]
        stem = view_stem(cam.name, i)
        gt = truth_of(capture, cam.name, cam.width, cam.height)
        if gt is None:
            raise SystemExit(f"{capture / 'images'} has no photo named {Path(cam.name).stem}.*: pass the "
                             "capture the scene was made from (--capture)")  # fmt: skip
        up = run / "0_refine" / "unseen" / f"{stem}.png"
        unseen = read_mask(up, mask.shape) if up.is_file() else mask
        tiles = []
        for s in STAGES:
            p = run / s / "images" / f"{stem}.png"
            if not p.is_file():
                continue
            img = read_image(p)
            both = mask & unseen
            rec = {"m_psnr": metrics.masked_psnr(img, gt, mask),
                   "u_psnr": metrics.masked_psnr(img, gt, both) if both.any() else None,
                   "bbox_gmsd": metrics.bbox_gmsd(img, gt, mask),
                   "hf": metrics.hf_ratio(img, gt, mask)}  # fmt: skip
            js = run / s / "views" / f"{stem}.json"
            if js.is_file():
                v = json.loads(js.read_text())
                rec["residual"] = v.get("residual_written", v.get("residual_after"))
                rec["status"] = v.get("status")
            per[s].append(rec)
            tiles.append(img)
        box = metrics.bbox_crop(mask, pad=8)
        if tiles and box is not None:
            from crop_grid import tile_row

            rows.append(tile_row([t[box] for t in tiles + [gt]], cell))
    out = {}
    for s, recs in per.items():
        if not recs:
            continue

        def mean(key, recs=recs):
            vals = [r[key] for r in recs if r.get(key) is not None and np.isfinite(r[key])]
            return float(np.mean(vals)) if vals else None

        statuses = [r.get("status") for r in recs if r.get("status")]
        out[s] = {"views": len(recs), "m_psnr": mean("m_psnr"), "u_psnr": mean("u_psnr"),
                  "bbox_gmsd": mean("bbox_gmsd"), "hf": mean("hf"), "residual": mean("residual"),
                  "statuses": {k: statuses.count(k) for k in sorted(set(statuses))},
                  "seconds": stage_seconds(run, s)}  # fmt: skip
    width = max((r.shape[1] for r in rows), default=0)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1) for r in rows]
    return out, (to_uint8(np.concatenate(rows, 0)) if rows else None)


def fmt(v, nd=3) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--capture", type=Path, default=default_data().parent / "cup_capture")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    head = ("run", "stage", "views", "m-PSNR", "unseen PSNR", "bbox GMSD", "HF ratio", "residual to ref",
            "written", "s")  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for run in a.runs:
        res, crops = score_run(run, a.capture)
        for s, r in res.items():
            lines.append(f"| {run.name} | {s} | {r['views']} | {fmt(r['m_psnr'], 2)} | "
                         f"{fmt(r['u_psnr'], 2)} | "
                         f"{fmt(r['bbox_gmsd'])} | {fmt(r['hf'])} | {fmt(r['residual'], 4)} | "
                         f"{', '.join(f'{k} {v}' for k, v in r['statuses'].items()) or '-'} | "
                         f"{fmt(r['seconds'], 0)} |")  # fmt: skip
        if a.out is not None and crops is not None:
            a.out.mkdir(parents=True, exist_ok=True)
            write_png(a.out / f"{run.name}_crops.png", crops)
    table = "\n".join(lines)
    print(table)
    if a.out is not None:
        (a.out / "fill_truth.md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
