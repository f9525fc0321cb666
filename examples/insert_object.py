"""Insert a second cup into the real cup capture from ONE edited photo, then look at it from every view.

    python examples/insert_object.py [--data ../shared/data/cup_capture] [--out runs/insert_cup]
        [--edited-view 24 --target X Y] [--source-view 32 --polygon X0 Y0 X1 Y1 ...]
        [--train 24 --held-out 8] [--resolution 0.2] [--iters 500 --ted-iters 400] [--edit-only]

What it does, step by step (everything it writes lies in --out):
1. Loads the capture (77 phone photos of a white cup on a wooden desk, COLMAP poses). The photos are
   stored sideways; every view is turned by quarter turns so that the desk's normal (a RANSAC plane
   of the sparse points) points up in it, camera and image together (the same rays): the one-photo
   lift takes the image's bottom for the side of the surface.
2. Cuts the cup out of --source-view with a hand-given polygon (the default traces the cup in view
   32), feathers its edge into a soft alpha and pastes it onto the wood beside the real cup in
   --edited-view, its bottom centre on the --target pixel and scaled for the depth it lands at (the
   two contacts' depths on the desk plane): `edited.png`, the one input a user has (`paste_mask.png`:
   where it differs from the capture; `source_cut.png`: the cut).
3. Runs the one-photo insertion (`coin_cl.inpaint(..., edited_ref=edited.png)`, regions derived) on
   a subset of the views: --train training views and --held-out views nobody trains on, spread
   evenly over the capture's azimuths around the real cup, at --resolution with explicit step counts
   (Ref-GS --iters, TE-D fine-tune --ted-iters, no adversarial phase: it costs the most per step and
   sharpens toward the initial images, which here are a warp). The run folder is OUT/run.
4. Writes `crops.png`: every view of the subset (sorted by azimuth from the edited view; label: view,
   azimuth / elevation in degrees, train / HO = held out / edited), cropped around the derived region:
   the capture with the inserted object's projected outline, the lift warped into the view (stage 1's
   image; for held-out views the same warp, computed here) and the final render (a view where the
   scene hides the object whole is cropped around its outline and labelled "hidden"); `regions.png`,
   stage 1's sheet of the derived regions on every training view; `views.json`, the figures. With
   --lift-only it stops before training and writes `lift_crops.png` without the render column.

Runtime: 3.8 minutes on 2 CPU cores (AMD EPYC, Intel's OpenCL CPU runtime; --edit-only and
--lift-only: seconds). docs/RUN.md, "Insertion on a real capture", says what the crop grid shows
view by view.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from coin_cl.pipeline.insert_config import PROFILES  # no torch: coin_cl imports lazily

# The defaults' hand-given cut: the cup in view 32 (turned upright, 600x800 pixels), lid, body and base,
# without its strap; and where its bottom centre goes in view 24: the wood to the real cup's left.
CUP_POLYGON_32 = ((270, 250), (272, 212), (300, 200), (330, 196), (380, 192), (420, 190), (470, 190),
                  (476, 205), (474, 240), (464, 262), (445, 300), (438, 360), (430, 420), (420, 480),
                  (414, 530), (408, 560), (395, 575), (365, 583), (335, 584), (305, 578), (290, 565),
                  (281, 540), (280, 470), (279, 400), (279, 300), (277, 268))  # fmt: skip
TARGET_24 = (150.0, 545.0)
# The soft edge of the pasted cup: its hard mask is eroded by this many px and blurred by this sigma
# (px of the edited view), so the edge blends over about 2 px instead of a hard cut.
FEATHER_ERODE = 1
FEATHER_SIGMA = 1.2
# The crop grid shows this share of the region's larger side around it on every side.
CROP_CONTEXT = 0.35
# Sparse points within this height of the desk plane are the desk (scene units: the capture's).
DESK_TOL = 0.06


def default_data() -> Path:
    env = os.environ.get("COIN_DATA")
    base = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return base / "cup_capture"


# -- views turned upright ---------------------------------------------------------------------------


def turn_camera(cam, k: int):
    """`cam` for its image turned clockwise by k quarter turns (np.rot90(img, -k)): the same rays.
    One turn maps pixel (u, v) of a W x H image to (H - v, u); camera axes (x, y, z) -> (-y, x, z)."""
    from coin_cl.scene.types import Camera

    K, V, w, h = cam.K.copy(), cam.viewmat.copy(), cam.width, cam.height
    turn = np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    for _ in range(k % 4):
        K = np.array([[K[1, 1], 0, h - K[1, 2]], [0, K[0, 0], K[0, 2]], [0, 0, 1]])
        V = turn @ V
        w, h = h, w
    return Camera(K=K, viewmat=V, width=w, height=h, name=cam.name)


def quarter_turns(cam, up: np.ndarray) -> int:
    """Clockwise quarter turns that bring the world direction `up` (3,) closest to the image's up."""
    x, y = (cam.viewmat[:3, :3] @ np.asarray(up, np.float64))[:2]  # camera frame; image up is -y
    score = []
    for _ in range(4):  # each clockwise turn maps the camera's (x, y) to (-y, x)
        score.append(-y)
        x, y = -y, x
    return int(np.argmax(score))


def upright(scene, up: np.ndarray):
    """`scene` with every view turned by quarter turns so that `up` points up in it."""
    cams, imgs, masks = [], [], []
    for cam, img, m in zip(scene.cameras, scene.images, scene.masks, strict=True):
        k = quarter_turns(cam, up)
        cams.append(turn_camera(cam, k))
        imgs.append(np.ascontiguousarray(np.rot90(img, -k)))
        masks.append(np.ascontiguousarray(np.rot90(m, -k)))
    return replace(scene, cameras=cams, images=imgs, masks=masks, priors={}, extras={})


def subset(scene, idx: list[int], test: list[int]):
    """The views `idx` of `scene` (in that order); those also in `test` are its held-out views."""
    return replace(
        scene,
        cameras=[scene.cameras[i] for i in idx],
        images=[scene.images[i] for i in idx],
        masks=[scene.masks[i] for i in idx],
        train_idx=[j for j, i in enumerate(idx) if i not in test],
        test_idx=[j for j, i in enumerate(idx) if i in test],
        priors={},
        extras={},
        near=None if scene.near is None else np.asarray(scene.near)[idx],
        far=None if scene.far is None else np.asarray(scene.far)[idx],
        ref_view=None,
    )


# -- the desk and the cup -----------------------------------------------------------------------------


def desk_and_object(points: np.ndarray, centers: np.ndarray, seed: int = 0) -> dict:
    """The desk and where the object on it stands, from the sparse `points` [N, 3] and the camera
    `centers` [V, 3]: {"plane": Plane (RANSAC, normal toward the cameras), "base": (3,) on the desk
    under the object, "e1", "e2": (3,) unit axes along the desk}. The base is the mean (along the
    desk) of the points above it near the densest cell of their 2D histogram: the real cup's
    points, which lean to its textured side, so it is the azimuths' reference, not its axis."""
    from coin_cl.scene.virtual_object import fit_plane

    P = np.asarray(points, np.float64)
    plane = fit_plane(P, DESK_TOL, centers.mean(0), seed=seed)
    n, h = plane.normal, plane.distance(P)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    q = np.stack([P @ e1, P @ e2], 1)
    above = (h > 5 * DESK_TOL) & (h < np.percentile(h, 99))
    H, xe, ye = np.histogram2d(q[above, 0], q[above, 1], bins=40)
    i, j = np.unravel_index(H.argmax(), H.shape)
    c0 = np.array([(xe[i] + xe[i + 1]) / 2, (ye[j] + ye[j + 1]) / 2])
    c = q[above & (np.linalg.norm(q - c0, axis=1) < 2 * (xe[1] - xe[0]))].mean(0)
    return {"plane": plane, "base": plane.d * n + c[0] * e1 + c[1] * e2, "e1": e1, "e2": e2}


def azimuths(cams, base: np.ndarray, normal: np.ndarray, e1: np.ndarray, e2: np.ndarray):
    """(azimuth degrees about `normal` through `base`, elevation degrees) of each camera centre."""
    v = np.array([c.center for c in cams]) - base
    hgt = v @ normal
    hor = v - np.outer(hgt, normal)
    az = np.degrees(np.arctan2(hor @ e2, hor @ e1))
    return az, np.degrees(np.arctan2(hgt, np.linalg.norm(hor, axis=1)))


# -- cut and paste ------------------------------------------------------------------------------------


def ray_on_plane(cam, uv, plane) -> np.ndarray:
    """The point (3,) where the ray of pixel `uv` (x, y; centres at +0.5) of `cam` meets `plane`.
    Raises ValueError when it does not (parallel, or behind the camera)."""
    c = cam.center
    d = cam.unproject(np.array([uv], np.float64), np.ones(1))[0] - c
    den = d @ plane.normal
    t = (plane.d - c @ plane.normal) / den if abs(den) > 1e-12 else -1.0
    if not t > 0:
        raise ValueError(f"pixel {tuple(uv)} of view {cam.name} does not look at the desk")
    return c + t * d


def polygon_mask(polygon, height: int, width: int) -> np.ndarray:
    """A hand-given polygon [(x, y), ...] (pixel corners, the image's pixels) -> (H, W) bool."""
    pts = np.round(np.asarray(polygon, np.float64)).astype(np.int32)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
        raise ValueError(f"the polygon has shape {pts.shape}: give at least 3 (x, y) corners")
    m = np.zeros((height, width), np.uint8)
    cv2.fillPoly(m, [pts], 1)
    return m.astype(bool)


def soft_alpha(mask: np.ndarray, erode: int = FEATHER_ERODE, sigma: float = FEATHER_SIGMA) -> np.ndarray:
    """A hard mask (H, W) bool -> alpha (H, W) float32 in [0, 1]: eroded by `erode` px, then blurred."""
    m = mask.astype(np.uint8)
    if erode > 0:
        m = cv2.erode(m, np.ones((2 * erode + 1, 2 * erode + 1), np.uint8))
    a = m.astype(np.float32)
    if sigma > 0:
        a = cv2.GaussianBlur(a, (0, 0), sigma)
    a[a < 1.0 / 255.0] = 0.0  # no faint halo far out: outside the paste the photo stays untouched
    return np.clip(a, 0.0, 1.0)


def paste(target: np.ndarray, source: np.ndarray, alpha: np.ndarray, src_anchor, dst_anchor,
          scale: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """`source` (h, w, 3) float with `alpha` (h, w) scaled by `scale` about `src_anchor` (x, y px)
    and moved onto `dst_anchor` of `target` (H, W, 3) float, blended by the alpha. Returns (edited
    (H, W, 3) float32, pasted (H, W) bool: where the warped alpha is > 0). Outside `pasted` the
    result is `target` exactly."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"paste scale is {scale!r}: give a positive finite number")
    H, W = target.shape[:2]
    sx, sy = src_anchor
    dx, dy = dst_anchor
    # OpenCV's pixel centres are at integers, the anchors' (coin_cl's) at +0.5
    tx, ty = (dx - 0.5) - scale * (sx - 0.5), (dy - 0.5) - scale * (sy - 0.5)
    M = np.array([[scale, 0.0, tx], [0.0, scale, ty]], np.float64)
    # shrinking: blur first so the warp's bilinear samples do not alias the source's texture
    src, a = np.asarray(source, np.float32), np.asarray(alpha, np.float32)
    if scale < 0.8:
        s = 0.5 / scale - 0.5
        src, a = cv2.GaussianBlur(src, (0, 0), s), cv2.GaussianBlur(a, (0, 0), s)
    ws = cv2.warpAffine(src, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    wa = cv2.warpAffine(a, M, (W, H), flags=cv2.INTER_LINEAR, borderValue=0.0)
    wa[wa < 1.0 / 255.0] = 0.0
    pasted = wa > 0
    out = np.asarray(target, np.float32).copy()
    out[pasted] = wa[pasted, None] * ws[pasted] + (1 - wa[pasted, None]) * out[pasted]
    return np.clip(out, 0.0, 1.0), pasted


def make_edit(scene, k: int, j: int, plane, polygon, target) -> dict:
    """The edited photo of view k: the object inside `polygon` (pixels of view j) pasted into view k
    with its bottom-centre on the desk pixel `target` (x, y of view k), scaled for the depth it lands
    at (the ratio of the two contacts' camera depths, and of the two focal lengths). Returns
    {"edited" (H, W, 3), "pasted" (H, W) bool, "hard_src" (the cut in view j), "scale"}."""
    cam_k, cam_j = scene.cameras[k], scene.cameras[j]
    hard = polygon_mask(polygon, cam_j.height, cam_j.width)
    ys, xs = np.nonzero(hard)
    bottom = ys.max() + 1.0
    src_anchor = (float(xs[ys >= ys.max() - 2].mean()) + 0.5, bottom)
    S = ray_on_plane(cam_j, src_anchor, plane)
    T = ray_on_plane(cam_k, target, plane)
    zj = float(cam_j.project(S[None])[1][0])
    zk = float(cam_k.project(T[None])[1][0])
    scale = (cam_k.K[0, 0] / zk) / (cam_j.K[0, 0] / zj)
    alpha = soft_alpha(hard)
    edited, pasted = paste(scene.images[k], scene.images[j], alpha, src_anchor, tuple(target), scale)
    ys, xs = np.nonzero(pasted)
    h, w = cam_k.height, cam_k.width
    if not len(ys) or ys.min() == 0 or xs.min() == 0 or ys.max() == h - 1 or xs.max() == w - 1:
        print(f"warning: the pasted object is cut by the border of view {cam_k.name}: move --target")
    return {"edited": edited, "pasted": pasted, "hard_src": hard, "scale": float(scale), "contact": T}


# -- the views, the run and the crop grid -------------------------------------------------------------


def pick_views(rel_az: np.ndarray, k: int, n_train: int, n_held: int) -> tuple[list[int], list[int]]:
    """(views, held_out): k and the n_train + n_held - 1 views nearest evenly spaced azimuths over the
    capture's range (`rel_az`: degrees from view k, per view), sorted by azimuth; n_held of them
    (never k), evenly spread over that order, are held out."""
    n = n_train + n_held
    if n > len(rel_az) or n_train < 2 or n_held < 0:
        raise ValueError(f"--train {n_train} --held-out {n_held}: give at least 2 training views and at "
                         f"most {len(rel_az)} views in all")  # fmt: skip
    chosen = [k]
    for t in np.linspace(rel_az.min(), rel_az.max(), n - 1):
        free = [int(i) for i in np.argsort(np.abs(rel_az - t)) if int(i) not in chosen]
        chosen.append(free[0])
    chosen.sort(key=lambda i: rel_az[i])
    others = [i for i in chosen if i != k]
    step = len(others) / max(n_held, 1)
    held = [others[int(step * (m + 0.5))] for m in range(n_held)]
    return chosen, held


def region_grid(
    rows: list[tuple[str, np.ndarray, list[np.ndarray]]], cell: int, per_row: int = 2
) -> np.ndarray:
    """Crop tiles of several views -> one uint8 grid: each view's equal-size tiles side by side
    (`benchmarks/crop_grid.tile_row`), the outline (H, W) bool drawn in green on its first tile and
    its label written there; `per_row` views a row."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from crop_grid import tile_row

    from coin_cl.scene.io import to_uint8

    strips = []
    for label, outline, tiles in rows:
        strip = np.ascontiguousarray(to_uint8(tile_row(tiles, cell)))
        h, w = tiles[0].shape[:2]
        sc = cell / max(h, w)
        size = (max(1, round(w * sc)), max(1, round(h * sc)))
        o = cv2.resize(outline.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(o, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(strip, contours, -1, (0, 255, 0), 1)
        cv2.putText(strip, label, (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(strip, label, (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
        strips.append(strip)
    while len(strips) % per_row:
        strips.append(np.full_like(strips[0], 255))
    lines = [np.concatenate(strips[r : r + per_row], axis=1) for r in range(0, len(strips), per_row)]
    return np.concatenate(lines, axis=0)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data(), help="the cup capture folder")
    ap.add_argument("--out", type=Path, default=Path("runs/insert_cup"))
    ap.add_argument("--edited-view", default="24", help="the view the cup is pasted into (name)")
    ap.add_argument("--target", type=float, nargs=2, default=TARGET_24, metavar=("X", "Y"),
                    help="the pasted cup's bottom centre in the edited (upright) view")  # fmt: skip
    ap.add_argument("--source-view", default="32", help="the view the cup is cut out of (name)")
    ap.add_argument(
        "--polygon",
        type=float,
        nargs="+",
        default=None,
        metavar="X Y",
        help="the cut in the (upright) source view: x0 y0 x1 y1 ... (default: the cup in 32)",
    )
    ap.add_argument("--train", type=int, default=24, help="training views (the edited one included)")
    ap.add_argument("--held-out", type=int, default=8, help="views left out of training, rendered")
    ap.add_argument("--resolution", type=float, default=0.2, help="working scale of the 800x600 photos")
    ap.add_argument("--iters", type=int, default=500, help="Ref-GS steps")
    ap.add_argument("--ted-iters", type=int, default=400, help="TE-D fine-tune steps (no adversarial phase)")
    ap.add_argument("--max-points", type=int, default=60_000,
                    help="cap on the lifted points (InsertConfig.max_points): they seed Ref-GS")  # fmt: skip
    ap.add_argument("--cell", type=int, default=180, help="crop tile size in the grid (px)")
    ap.add_argument("--profile", choices=PROFILES, default="revolve",
                    help="the object's shape behind its silhouette (InsertConfig.profile): a cup is "
                         "round")  # fmt: skip
    ap.add_argument("--edit-only", action="store_true", help="stop after writing the edited photo")
    ap.add_argument("--lift-only", action="store_true",
                    help="stop after stage 1's crop grid (the derived regions and the lift in every view; "
                         "no training, seconds)")  # fmt: skip
    args = ap.parse_args(argv)
    if args.polygon is None:
        if args.source_view != "32":
            raise SystemExit("give --polygon X0 Y0 X1 Y1 ... of the object in --source-view")
        polygon = CUP_POLYGON_32
    elif len(args.polygon) % 2 or len(args.polygon) < 6:
        raise SystemExit(f"--polygon takes x y pairs, at least 3: got {len(args.polygon)} numbers")
    else:
        polygon = np.reshape(args.polygon, (-1, 2))

    import torch

    import coin_cl
    from coin_cl import metrics
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.insert import load_edited, read_lift
    from coin_cl.pipeline.insert_config import InsertConfig
    from coin_cl.pipeline.insert_geometry import derive_masks, footprint, run_insert_derived
    from coin_cl.scene.io import read_image, to_uint8, write_png, write_text
    from coin_cl.scene.masks import write_mask

    t0 = time.perf_counter()

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:5.0f} s] {msg}", flush=True)

    out: Path = args.out
    full = coin_cl.load_scene(args.data, n_test=0, priors=False, undistort=False)
    say(f"loaded {len(full)} views of {args.data}")
    centers = np.array([c.center for c in full.cameras])
    geo = desk_and_object(full.points, centers)
    plane = geo["plane"]
    full = upright(full, plane.normal)
    k_all, j_all = full.index(args.edited_view), full.index(args.source_view)
    az, el = azimuths(full.cameras, geo["base"], plane.normal, geo["e1"], geo["e2"])
    rel = (az - az[k_all] + 180.0) % 360.0 - 180.0
    say(f"desk normal {np.round(plane.normal, 3)} ({plane.inliers} points); every view turned upright; "
        f"camera azimuths about the cup {rel.min():.0f}..{rel.max():.0f} degrees from view "
        f"{args.edited_view}")  # fmt: skip

    edit = make_edit(full, k_all, j_all, plane, polygon, args.target)
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "edited.png", to_uint8(edit["edited"]))
    write_mask(out / "paste_mask.png", edit["pasted"])
    dim = 0.25 + 0.75 * edit["hard_src"][..., None]
    write_png(out / "source_cut.png", to_uint8(full.images[j_all] * dim))
    say(
        f"cut the cup out of view {args.source_view}, pasted it into view {args.edited_view} at "
        f"{args.target} (scale {edit['scale']:.2f}, {int(edit['pasted'].sum())} px): {out / 'edited.png'}"
    )
    if args.edit_only:
        return {"edited": out / "edited.png", **edit}

    views, held = pick_views(rel, k_all, args.train, args.held_out)
    scene = subset(full, views, held)
    k = views.index(k_all)
    names = [c.name for c in scene.cameras]
    info = {
        "views": {nm: {"azimuth": round(float(rel[v]), 1), "elevation": round(float(el[v]), 1),
                       "held_out": v in held} for nm, v in zip(names, views)},  # fmt: skip
        "edited_view": args.edited_view, "source_view": args.source_view, "target": list(args.target),
        "paste_scale": edit["scale"], "resolution": args.resolution, "iters_refgs": args.iters,
        "iters_ted_finetune": args.ted_iters, "max_points": args.max_points,
    }  # fmt: skip
    listed = ", ".join(f"{Path(nm).stem}{'(HO)' if v in held else ''} {rel[v]:+.0f}"
                       for nm, v in zip(names, views))  # fmt: skip
    say(
        f"{len(scene.train_idx)} training views, {len(held)} held out (HO), azimuth from the edited "
        f"view: {listed}"
    )

    icfg = InsertConfig(regions="derive", max_points=args.max_points, profile=args.profile)
    info["profile"] = args.profile
    res = None
    if not args.lift_only:
        # the view by its file name: a bare "24" would also name index 24 of a larger subset
        cfg = CoInConfig(resolution=args.resolution, ref=scene.cameras[k].name, iters_refgs=args.iters,
                         iters_ted_finetune=args.ted_iters, iters_ted_adversarial=0, insert=icfg)  # fmt: skip
        t_run = time.perf_counter()
        res = coin_cl.inpaint(scene, out / "run", config=cfg, edited_ref=out / "edited.png")
        info["run_minutes"] = round((time.perf_counter() - t_run) / 60, 2)
        say(f"run done in {info['run_minutes']:.1f} min: {out / 'run'}")

    # every view of the subset at the working size: derived regions, the lift's warp, the render
    work = scene.resized(args.resolution)
    cam_k = work.cameras[k]
    full_k = (scene.cameras[k].width, scene.cameras[k].height)
    edited = load_edited(out / "edited.png", (cam_k.width, cam_k.height), full_k)
    regions = derive_masks(edited, work, work.masks, k, "edited.png", icfg)
    warp_dir = out / "warp_all_views"
    if warp_dir.exists():
        shutil.rmtree(warp_dir)
    run_insert_derived(work, regions, list(range(len(work))), k, edited, warp_dir, icfg, "edited.png")
    lift = read_lift(warp_dir if res is None else out / "run" / "1_inpaint")
    rows = []
    for i in sorted(range(len(work)), key=lambda i: rel[views[i]]):
        cam, stem = work.cameras[i], Path(work.cameras[i].name).stem
        foot = footprint(lift.points, cam)
        info["views"][cam.name]["object_px"] = int(foot.sum())
        # a view where the scene hides the object whole (an empty region) is cropped around where
        # the object would be, to show that the capture stays in front of it
        around = regions[i] if regions[i].any() else foot
        if not around.any():
            continue
        ys, xs = np.nonzero(around)
        # context around the region (the desk under it, the real cup beside it)
        pad = max(8, round(CROP_CONTEXT * max(np.ptp(ys), np.ptp(xs))))
        crop = metrics.bbox_crop(around, pad=pad)
        warp = read_image(warp_dir / "images" / f"{stem}.png")
        tiles = [work.images[i][crop], warp[crop]]
        if res is not None:
            with torch.no_grad():
                render = res.model.render(cam, 10**9).image.clamp(0, 1).numpy()
            write_png(out / "renders" / f"{stem}.png", to_uint8(render))
            tiles.append(render[crop])
        tag = "edited" if i == k else ("HO" if i in work.test_idx else "train")
        tag += "" if regions[i].any() else ", hidden"
        label = f"{stem} {rel[views[i]]:+.0f}/{el[views[i]]:.0f} {tag}"
        rows.append((label, foot[crop], tiles))
    grid = "lift_crops.png" if res is None else "crops.png"
    write_png(out / grid, region_grid(rows, args.cell))
    shutil.copyfile(warp_dir / "edit" / "regions.png", out / "regions.png")
    info["minutes"] = round((time.perf_counter() - t0) / 60, 2)
    write_text(out / "views.json", json.dumps(info, indent=1))
    say(
        f"crop grid (the capture with the object's outline | the lift warped in | the render; label: view, "
        f"azimuth/elevation in degrees from the edited view): {out / grid}; regions: "
        f"{out / 'regions.png'}; {info['minutes']:.1f} min in all"
    )
    return {"out": out, "result": res, "info": info}


if __name__ == "__main__":
    main()
