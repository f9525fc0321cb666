"""A removal scene with ground truth from any posed real capture: a virtual textured box
(`coin_cl.scene.virtual_object`) painted into the training views; every K-th view is a test view,
left untouched (its image file copied byte for byte), whose mask is the box's footprint (the region
a removal is scored on). docs/VIRTUAL_OBJECTS.md is the user-facing protocol.

Guarantees (each checked by tests/test_prepare_virtual_scene.py on the synthetic room):
- a training view's mask is every pixel whose square any ray of the box hits, and every one of those
  pixels holds the box's colour: the method never receives a real pixel inside a training mask;
- the sparse points are triangulated (`triangulate.triangulate_known_poses`, poses fixed) from the
  training images as painted; no test view takes part, and points inside the box are dropped;
- placement: the box stands on a plane RANSAC-fitted to the capture's sparse points near the chosen
  centre, up axis = the plane normal;
- occlusion: the capture's sparse points are the scene's depth proxy (`virtual_object.occluders`;
  a point in the box's footprint more than `occlusion_margin` x the box's smallest side in front of
  the box hides it), and a camera below the supporting plane sees the box through the surface. A
  view where the box would be hidden, or that the box reaches behind, is left out of the scene
  (training and test alike: a painted box there would be physically wrong, and a test view's scored
  region would hold real geometry in front of the box). A box that cuts through real geometry
  (sparse points inside it) is refused; `--auto` only picks placements hidden in few views;
- a test candidate the box does not appear in (empty footprint) stays a training view, unpainted
  with an empty mask (which is what a real photo of that view would show).

Output: coin-cl's own scene layout (docs/SCENES.md, 3): scene.json, images/ (training views
<stem>.png, test views the capture's files), masks/<stem>.png, points3D.ply, plus
virtual_object.json (the box, plane, per-view status, coverage, timings) and contact_sheet.png.
It is written to a scratch folder beside `out` and renamed at the end: nothing half written remains.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..scene.folder import near_far
from ..scene.io import write_png, write_text
from ..scene.loader import load_scene
from ..scene.ply import write_points_ply
from ..scene.types import Camera, Scene
from ..scene.virtual_object import (
    Plane,
    VirtualBox,
    below_plane,
    box_on_plane,
    coverage,
    fit_plane,
    occluders,
    points_inside,
    render_box,
    silhouette,
)
from .triangulate import TriangulateConfig, triangulate_known_poses

log = logging.getLogger(__name__)

# Box proportions --auto uses (x, y, up), scaled to the target coverage.
AUTO_ASPECT = np.array([1.0, 0.75, 0.85])
# Contact sheet: thumbnail width in pixels and columns.
SHEET_THUMB = 200
SHEET_COLS = 8


@dataclass
class VirtualSceneConfig:
    """Options of `make_virtual_scene`.

    test_every: every K-th view in natural name order (1, 2, ..., 10: numbers compared as numbers),
        starting with the first, is a test view.
    seed: the box texture's colours; with --auto also the yaw and the RANSAC samples.
    supersample: rays per pixel side when shading the box.
    plane_neighbours: how many capture points nearest the chosen centre the plane is fitted to.
    plane_threshold: RANSAC inlier distance as a fraction of the box's largest base side.
    occlusion_margin: a point in front of the box by more than this x the box's smallest side hides it.
    occlusion_points: a view is occluded when at least this many points hide the box (one or two are
        floating outliers of the SfM model).
    inside_shrink: sparse points inside the box shrunk by this x its smallest side per side mean the
        box cuts through real geometry (refused); `inside_points` of them are tolerated as outliers.
    drop_margin: triangulated points inside the box grown by this x its smallest side per side are
        dropped (its painted surface included).
    auto_coverage: --auto sizes the box so its median coverage over the views is this fraction.
    auto_whole: --auto wants the box whole (not cut by the border) in at least this fraction of the
        views it appears in.
    auto_max_excluded: --auto accepts a placement hidden (or otherwise excluded) in at most this
        fraction of the views.
    triangulate: feature / matching options of the point triangulation.
    """

    test_every: int = 8
    seed: int = 0
    supersample: int = 3
    plane_neighbours: int = 300
    plane_threshold: float = 0.03
    occlusion_margin: float = 0.1
    occlusion_points: int = 10
    inside_shrink: float = 0.1
    inside_points: int = 5
    drop_margin: float = 0.02
    auto_coverage: float = 0.05
    auto_whole: float = 0.7
    auto_max_excluded: float = 0.2
    triangulate: TriangulateConfig = field(default_factory=TriangulateConfig)


@dataclass
class BoxSpec:
    """A placement asked for: a point near which the box stands (world), its extents (x, y, up,
    world units) and its yaw about the surface normal (degrees, from the world x axis projected on
    the surface)."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0


def natural_order(names: list[str]) -> list[int]:
    """Indices of `names` sorted with digit runs compared as numbers ("2.jpg" before "10.jpg")."""

    def key(n: str):
        return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", n) if t]

    return sorted(range(len(names)), key=lambda i: key(names[i]))


def check_pinhole(capture: Path) -> None:
    """The test views are the capture's files byte for byte, so the capture must need no
    undistortion; a camera model with distortion is an error saying what to run."""
    from ..scene.colmap import pinhole_for
    from ..scene.folder import image_dir, open_folder, read_poses
    from ..scene.io import list_images

    imgdir = image_dir(capture, None)
    poses = read_poses(open_folder(capture, imgdir, list_images(imgdir)), undistort=False)
    for cid, cc in poses.cameras.items():
        if pinhole_for(cc, source=str(capture))[1] is not None:
            raise ValueError(
                f"{capture}: camera {cid} ({cc.model}) has lens distortion; the test views must be the "
                "capture's files unchanged: run `colmap image_undistorter` first and use its output"
            )


# --------------------------------------------------------------------------------------- placement


def view_status(box: VirtualBox, plane: Plane, cam: Camera, points: np.ndarray,
                cfg: VirtualSceneConfig) -> tuple[str, int]:  # fmt: skip
    """("behind" | "below_plane" | "empty" | "occluded" | "drawn", occluding points) for one view."""
    if silhouette(box, cam) is None:
        return "behind", 0
    if below_plane(plane, cam):
        return "below_plane", 0
    cov, _ = coverage(box, cam)
    if not cov > 0:
        return "empty", 0
    n = occluders(box, cam, points, cfg.occlusion_margin * box.size.min())
    return ("occluded" if n >= cfg.occlusion_points else "drawn"), n


def place_box(scene: Scene, spec: BoxSpec, cfg: VirtualSceneConfig) -> tuple[VirtualBox, Plane]:
    """The box of `spec` standing on the plane fitted to the capture's points nearest its centre.
    Raises ValueError when the box would cut through real geometry."""
    pts = np.asarray(scene.points, np.float64)
    c = np.asarray(spec.center, np.float64)
    if len(pts) < 3:
        raise ValueError(f"capture {scene.path} has {len(pts)} sparse points; a supporting plane needs more")
    near = pts[np.argsort(np.linalg.norm(pts - c, axis=1))[: cfg.plane_neighbours]]
    cams = np.mean([cam.center for cam in scene.cameras], axis=0)
    th = cfg.plane_threshold * max(spec.size[0], spec.size[1])
    plane = fit_plane(near, th, toward=cams, seed=cfg.seed)
    box = box_on_plane(plane, c, spec.size, spec.yaw, seed=cfg.seed)
    n_in = points_inside(box, pts, cfg.inside_shrink * box.size.min())
    if n_in > cfg.inside_points:
        raise ValueError(
            f"the box at {np.round(box.center, 3).tolist()} cuts through the scene ({n_in} sparse points "
            "inside it): move it with --box to free surface, or use --auto"
        )
    return box, plane


def auto_spec(scene: Scene, cfg: VirtualSceneConfig) -> BoxSpec:
    """A placement found automatically: on the dominant plane near the centre of interest (the
    point closest to all optical axes, projected on the plane), sized so the median coverage over
    the views is `auto_coverage`, whole in `auto_whole` of the views it appears in, excluded
    (hidden) in at most `auto_max_excluded` of them, cutting through no geometry.
    Candidates on a grid around the centre of interest, nearest first.
    Raises ValueError when none qualifies."""
    pts = np.asarray(scene.points, np.float64)
    centers = np.stack([c.center for c in scene.cameras])
    dirs = np.stack([c.camtoworld[:3, 2] for c in scene.cameras])
    # least-squares point nearest to every optical axis
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(centers, dirs):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    coi = np.linalg.lstsq(A, b, rcond=None)[0]
    dist = float(np.median(np.linalg.norm(centers - coi, axis=1)))
    plane = fit_plane(pts, 0.01 * dist, toward=centers.mean(axis=0), seed=cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    yaw = float(rng.uniform(0, 90))
    probe = box_on_plane(plane, coi, AUTO_ASPECT * 0.1 * dist, yaw)
    u, v = probe.axes[:, 0], probe.axes[:, 1]
    step = 0.08 * dist
    grid = [(i, j) for i in range(-6, 7) for j in range(-6, 7)]
    grid.sort(key=lambda ij: ij[0] ** 2 + ij[1] ** 2)
    for i, j in grid:
        p = plane.project(coi) + step * (i * u + j * v)
        size = AUTO_ASPECT * 0.1 * dist
        for _ in range(2):  # coverage grows as size^2
            covs = [coverage(box_on_plane(plane, p, size, yaw), c)[0] for c in scene.cameras]
            med = float(np.nanmedian(covs)) if np.isfinite(covs).any() else 0.0
            if not med > 0:
                break
            size = size * np.sqrt(cfg.auto_coverage / med)
        box = box_on_plane(plane, p, size, yaw)
        if points_inside(box, pts, cfg.inside_shrink * box.size.min()) > cfg.inside_points:
            continue
        status = [view_status(box, plane, c, pts, cfg)[0] for c in scene.cameras]
        excluded = sum(s in ("occluded", "behind", "below_plane") for s in status)
        if excluded > cfg.auto_max_excluded * len(status):
            continue
        shown = [k for k, s in enumerate(status) if s == "drawn"]
        whole = [coverage(box, scene.cameras[k])[1] for k in shown]
        if len(shown) < 0.6 * len(status) or np.mean(whole) < cfg.auto_whole:
            continue
        return BoxSpec(tuple(box.base.tolist()), tuple(box.size.tolist()), yaw)
    raise ValueError(
        f"--auto found no free placement near the centre of interest of {scene.path}; give one with --box"
    )


# ------------------------------------------------------------------------------------------ driver


def make_virtual_scene(capture: str | Path, out: str | Path, box: BoxSpec | None = None,
                       config: VirtualSceneConfig | None = None) -> dict:  # fmt: skip
    """Capture folder (any layout `load_scene` reads, pinhole cameras) -> removal scene in `out`
    (module doc). box: the placement; None: `auto_spec`. Returns the virtual_object.json document."""
    cfg = config or VirtualSceneConfig()
    capture, out = Path(capture), Path(out)
    if cfg.test_every < 2:
        raise ValueError(
            f"--test-every must be at least 2 (1 would leave no training view), got {cfg.test_every}"
        )
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} exists and is not empty; remove it or choose another --out")
    t_start = time.perf_counter()
    check_pinhole(capture)
    scene = load_scene(capture, n_test=0, priors=False, undistort=False)
    files = _image_files(scene)
    spec = box if box is not None else auto_spec(scene, cfg)
    vbox, plane = place_box(scene, spec, cfg)
    pts = np.asarray(scene.points, np.float64)
    order = natural_order(scene.names)
    test_cand = {i for k, i in enumerate(order) if k % cfg.test_every == 0}

    views, train, test, painted = [], [], [], {}
    for i in order:
        cam = scene.cameras[i]
        status, n_occ = view_status(vbox, plane, cam, pts, cfg)
        rec = {"name": cam.name, "status": status, "occluding_points": n_occ}
        if status in ("behind", "below_plane", "occluded"):
            rec["split"] = "excluded"
        else:
            r = render_box(vbox, cam, cfg.supersample) if status == "drawn" else None
            mask = r["mask"] if r is not None else np.zeros((cam.height, cam.width), bool)
            rec["coverage"] = float(mask.mean())
            rec["whole"] = bool(status == "drawn" and coverage(vbox, cam)[1])
            if i in test_cand and mask.any():
                rec["split"] = "test"
                test.append(i)
            else:
                rec["split"] = "train"
                train.append(i)
            painted[i] = (mask, r["rgb"] if r is not None else None)
        views.append(rec)
    if not test:
        raise ValueError(f"no test view shows the box (every {cfg.test_every}th view); lower --test-every")
    if len(train) < 3:
        raise ValueError(f"only {len(train)} training views remain; the box is hidden in most views: move it")
    images = {
        i: np.where(painted[i][0][..., None], painted[i][1], scene.images[i]) if painted[i][1] is not None
        else scene.images[i]
        for i in train
    }  # fmt: skip

    tmp = out.parent / f".{out.name}.tmp"
    if tmp.exists():
        raise FileExistsError(f"{tmp} is left from an interrupted run; remove it")
    try:
        t0 = time.perf_counter()
        tri = triangulate_known_poses([images[i] for i in train], [scene.cameras[i] for i in train],
                                      tmp / "work", cfg.triangulate)  # fmt: skip
        t_tri = time.perf_counter() - t0
        inside = vbox.contains(tri.points, grow=cfg.drop_margin * vbox.size.min())
        points, colors = tri.points[~inside], tri.colors[~inside]
        doc = _write(tmp, scene, files, train, test, images, painted, points, colors)
        doc_vo = {
            "generator": "coin_cl.prepare.virtual_scene",
            "capture": str(capture),
            "box": vbox.to_json(),
            "spec": asdict(spec),
            "auto": box is None,
            "plane": plane.to_json(),
            "config": {k: v for k, v in asdict(cfg).items() if k != "triangulate"},
            "triangulate": asdict(cfg.triangulate),
            "n_views": {
                "train": len(train),
                "test": len(test),
                "excluded": sum(v["split"] == "excluded" for v in views),
            },  # fmt: skip
            "coverage_train": _stats([v["coverage"] for v in views if v["split"] == "train"]),
            "coverage_test": _stats([v["coverage"] for v in views if v["split"] == "test"]),
            "points": {
                "triangulated": len(tri.points),
                "inside_box_dropped": int(inside.sum()),
                "kept": len(points),
                "pairs_matched": tri.n_pairs,
                # every view any kept point was triangulated from (training views only)
                "from_views": sorted({n for k, t in enumerate(tri.tracks) if not inside[k] for n in t}),
            },
            "seconds": {
                **{k: round(v, 1) for k, v in tri.seconds.items()},
                "triangulation_total": round(t_tri, 1),
            },
            "views": views,
        }
        contact_sheet(tmp / "contact_sheet.png", scene, order, views, images, painted)
        doc_vo["seconds"]["total"] = round(time.perf_counter() - t_start, 1)
        write_text(tmp / "virtual_object.json", json.dumps(doc_vo, indent=1))
        write_text(tmp / "scene.json", json.dumps(doc, indent=1))
        if out.exists():
            out.rmdir()  # empty (checked above)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return doc_vo


def _image_files(scene: Scene) -> list[Path]:
    from ..scene.folder import find_file, image_dir

    imgdir = image_dir(Path(scene.path), None)
    files = [find_file(imgdir, c.name) for c in scene.cameras]
    missing = [c.name for c, f in zip(scene.cameras, files) if f is None]
    if missing:
        raise FileNotFoundError(f"{imgdir}: image files {missing[:3]} not found")
    return files


def _stats(a: list[float]) -> dict:
    if not a:
        return {}
    a = np.asarray(a)
    return {"min": float(a.min()), "median": float(np.median(a)), "max": float(a.max()),
            "share_3_to_8_percent": float(((a >= 0.03) & (a <= 0.08)).mean())}  # fmt: skip


def _write(tmp: Path, scene: Scene, files: list[Path], train: list[int], test: list[int], images: dict,
           painted: dict, points: np.ndarray, colors: np.ndarray) -> dict:  # fmt: skip
    """images/, masks/, points3D.ply into `tmp`; returns the scene.json document (written last)."""
    keep = sorted(train + test)
    views, cams = [], []
    for i in keep:
        cam = scene.cameras[i]
        stem = Path(cam.name).stem
        if i in test:
            rel = f"images/{files[i].name}"
            (tmp / "images").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(files[i], tmp / rel)  # the ground truth, byte for byte
        else:
            rel = f"images/{stem}.png"
            write_png(tmp / rel, images[i])
        write_png(tmp / "masks" / f"{stem}.png", painted[i][0].astype(np.uint8) * 255)
        views.append({**cam.to_json(), "image": rel, "mask": f"masks/{stem}.png"})
        cams.append(cam)
    write_points_ply(tmp / "points3D.ply", points.astype(np.float32), colors)
    near, far = near_far(None, cams, points.astype(np.float32))
    return {
        "format": "coin-cl scene",
        "version": 1,
        "views": views,
        "train_idx": [keep.index(i) for i in train],
        "test_idx": [keep.index(i) for i in test],
        "ref_view": None,
        "near": None if near is None else near.tolist(),
        "far": None if far is None else far.tolist(),
        "points": "points3D.ply",
        # every pixel outside a training mask is the capture's own (no fringe, no shadow)
        "meta": {
            "generator": "coin_cl.prepare.virtual_scene",
            "masks": "exact",
            "capture": str(scene.path),
        },  # fmt: skip
    }


def contact_sheet(path: Path, scene: Scene, order: list[int], views: list[dict], images: dict,
                  painted: dict) -> None:  # fmt: skip
    """Thumbnails of every view in natural order: training views as painted, test views with the
    mask's outline in magenta, excluded views greyed; each labelled with name, split, coverage."""
    tiles = []
    for i, v in zip(order, views, strict=True):
        img = images.get(i, scene.images[i])
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8).copy()
        if v["split"] == "test":
            cnts, _ = cv2.findContours(
                painted[i][0].astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
            )
            cv2.drawContours(img, cnts, -1, (255, 0, 255), max(1, img.shape[1] // 200))
        elif v["split"] == "excluded":
            img = (img * 0.35).astype(np.uint8)
        h = round(img.shape[0] * SHEET_THUMB / img.shape[1])
        t = cv2.resize(img, (SHEET_THUMB, h), interpolation=cv2.INTER_AREA)
        label = f"{Path(v['name']).stem} {v['split']}"
        if "coverage" in v:
            label += f" {100 * v['coverage']:.1f}%"
        cv2.rectangle(t, (0, 0), (SHEET_THUMB, 16), (0, 0, 0), -1)
        cv2.putText(t, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    h = max(t.shape[0] for t in tiles)
    rows = []
    for k in range(0, len(tiles), SHEET_COLS):
        row = [
            np.pad(t, ((0, h - t.shape[0]), (0, 2), (0, 0)), constant_values=255)
            for t in tiles[k : k + SHEET_COLS]
        ]
        while len(row) < SHEET_COLS:
            row.append(np.full((h, SHEET_THUMB + 2, 3), 255, np.uint8))
        rows.append(np.pad(np.concatenate(row, axis=1), ((0, 2), (0, 0), (0, 0)), constant_values=255))
    write_png(path, np.concatenate(rows, axis=0))
