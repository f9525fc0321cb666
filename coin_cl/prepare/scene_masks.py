"""Masks for a prepared scene folder: one annotation (`annotate`) spread to every view
(`propagate`), written as `SCENE/masks/<name>.png` (0/255, editable in any paint program; the
loader reads them), `SCENE/masks_report.json` and `SCENE/masks_contact_sheet.png` (every view
with its mask outline: red = segmented, yellow = replaced by the 3D consensus, green frame = the
annotated view)."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..atomic import copy_file
from ..scene.colmap import pinhole_for, read_model
from ..scene.folder import image_dir
from ..scene.io import IMAGE_EXTS, read_image, to_uint8, write_png, write_text
from ..scene.types import Camera
from .annotate import box_mask, check_box, read_annotation, resolve_view, scribble_mask
from .holdout import read_test_list
from .propagate import PropagateConfig, PropagateResult, Segmenter, propagate_masks
from .sfm import image_size

log = logging.getLogger(__name__)

SHEET_THUMB = 240  # contact sheet thumbnail width, px
SHEET_COLS = 6
COLOURS = {
    "segment": (255, 40, 40),
    "consensus": (255, 220, 0),
    "annotation": (40, 255, 40),
    "empty": (0, 0, 0),
}


@dataclass
class Annotation:
    """The object in one view: exactly one of box (x0, y0, x1, y1), scribble (image path) or mask
    (image path). With `photos_dir` the box is in the pixels of that folder's photo of the view
    (scaled here to the prepared image); without, in the prepared image's pixels."""

    view: str | int
    box: tuple[float, float, float, float] | None = None
    scribble: str | Path | None = None
    mask: str | Path | None = None
    photos_dir: str | Path | None = None

    def __post_init__(self) -> None:
        given = [k for k in ("box", "scribble", "mask") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of --box, --scribble, --mask (got {given or 'none'})")


@dataclass
class PreparedViews:
    """A prepared folder's views: names, cameras, images (H, W, 3), points (N, 3), per-view tracks."""

    names: list[str]
    cameras: list[Camera]
    images: list[np.ndarray]
    points: np.ndarray
    seen: list[np.ndarray]


def visible_point_ids(scene_dir: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The prepared model's points (N, 3) sorted by point id (the order `load_scene` uses) and,
    per image name, the indices (into those points) of the points that image observes."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(Path(scene_dir) / "sparse" / "0"))
    ids = sorted(rec.points3D.keys())
    row = {pid: i for i, pid in enumerate(ids)}
    xyz = np.array([rec.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    seen = {}
    for im in rec.images.values():
        idx = [row[p.point3D_id] for p in im.points2D if p.has_point3D()]
        seen[im.name] = np.array(sorted(set(idx)), np.int64)
    return xyz, seen


def load_prepared(scene_dir: str | Path) -> PreparedViews:
    """The training views of a folder written by `run_sfm` (PINHOLE model in sparse/0, images/);
    held-out photos (`sparse/0/test.txt`) are not among them: their masks are given, not propagated."""
    root = Path(scene_dir)
    model_dir = root / "sparse" / "0"
    if not (model_dir / "images.bin").is_file():
        raise FileNotFoundError(
            f"{model_dir} holds no model; run `coin-cl prepare PHOTOS --out {root}` first"
        )
    model = read_model(model_dir)
    points, seen_by_name = visible_point_ids(root)
    held = set(read_test_list(root))
    names = sorted(n for n in model.images if n not in held)
    cams, imgs = [], []
    for n in names:
        cid, vm = model.images[n]
        K, dist, _ = pinhole_for(model.cameras[cid], f"{model_dir} camera {cid}")
        if dist is not None and np.any(dist):
            raise ValueError(f"{model_dir}: camera {cid} is not undistorted; run `coin-cl prepare` again")
        c = model.cameras[cid]
        cams.append(Camera(K, vm, c.width, c.height, n))
        imgs.append(read_image(image_dir(root, None) / n))
    return PreparedViews(names, cams, imgs, points, [seen_by_name[n] for n in names])


def reference_mask(
    views: PreparedViews, ann: Annotation, segment: Segmenter | None = None
) -> tuple[int, np.ndarray]:
    """The annotated view's index and its object mask (H, W) bool."""
    ref = resolve_view(ann.view, views.names)
    img, cam = views.images[ref], views.cameras[ref]
    if ann.box is not None:
        scale = 1.0
        if ann.photos_dir is not None:
            stem = Path(views.names[ref]).stem
            photo = next((p for p in Path(ann.photos_dir).glob(f"{stem}.*") if p.suffix in IMAGE_EXTS), None)
            if photo is None:
                raise FileNotFoundError(f"no photo named {stem}.* in {ann.photos_dir}")
            scale = cam.width / image_size(photo)[0]
        box = check_box([v * scale for v in ann.box], cam.width, cam.height, views.names[ref])
        return ref, box_mask(img, box, segment)
    if ann.scribble is not None:
        return ref, scribble_mask(img, read_annotation(ann.scribble, cam.width, cam.height), segment)
    return ref, read_annotation(ann.mask, cam.width, cam.height)


def contact_sheet(images: list[np.ndarray], masks: list[np.ndarray], names: list[str], source: list[str],
                  thumb: int = SHEET_THUMB, cols: int = SHEET_COLS) -> np.ndarray:  # fmt: skip
    """All views as thumbnails with their mask outlines and names: (H, W, 3) uint8."""
    h0, w0 = images[0].shape[:2]
    th = max(1, round(thumb * h0 / w0))
    rows = -(-len(images) // cols)
    sheet = np.full((rows * (th + 18), cols * thumb, 3), 255, np.uint8)
    for i, (img, m, n, s) in enumerate(zip(images, masks, names, source, strict=True)):
        t = cv2.resize(to_uint8(img), (thumb, th), interpolation=cv2.INTER_AREA)
        mt = cv2.resize(m.astype(np.uint8), (thumb, th), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(mt, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        colour = COLOURS.get(s, (255, 40, 40))
        cv2.drawContours(t, contours, -1, COLOURS["consensus"] if s == "consensus" else (255, 40, 40), 2)
        if s == "annotation":
            cv2.rectangle(t, (0, 0), (thumb - 1, th - 1), colour, 4)
        r, c = divmod(i, cols)
        y, x = r * (th + 18), c * thumb
        sheet[y : y + th, x : x + thumb] = t
        cv2.putText(sheet, f"{i} {Path(n).stem}"[:32], (x + 3, y + th + 13), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4, (0, 0, 0), 1, cv2.LINE_AA)  # fmt: skip
    return sheet


def write_masks(scene_dir: str | Path, views: PreparedViews, result: PropagateResult, ref: int) -> Path:
    """masks/ (written whole, then moved in place), masks_report.json, masks_contact_sheet.png."""
    root = Path(scene_dir)
    tmp = root / ".masks.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    for n, m in zip(views.names, result.masks, strict=True):
        write_png(tmp / f"{Path(n).stem}.png", m.astype(np.uint8) * 255)
    for n in read_test_list(root):  # the held-out photos' region masks were given: keep them
        src = root / "masks" / f"{Path(n).stem}.png"
        if src.is_file():
            copy_file(src, tmp / src.name)
    shutil.rmtree(root / "masks", ignore_errors=True)
    tmp.rename(root / "masks")
    report = {
        "reference_view": views.names[ref],
        "object_points": result.n_object_points,
        "depth_range": list(result.depth_range),
        "views": [
            {
                "name": n,
                "source": s,
                "consensus_iou": None if np.isnan(c) else round(c, 4),
                "area": int(m.sum()),
            }  # fmt: skip
            for n, s, c, m in zip(views.names, result.source, result.consistency, result.masks, strict=True)
        ],
        "check": [n for n, s in zip(views.names, result.source, strict=True) if s in ("consensus", "empty")],
    }
    write_text(root / "masks_report.json", json.dumps(report, indent=1))
    write_png(root / "masks_contact_sheet.png",
              contact_sheet(views.images, result.masks, views.names, result.source))  # fmt: skip
    return root / "masks"


def make_masks(scene_dir: str | Path, ann: Annotation, config: PropagateConfig | None = None,
               segment: Segmenter | None = None) -> PropagateResult:  # fmt: skip
    """Annotation -> masks for every view of a prepared folder, written beside it."""
    views = load_prepared(scene_dir)
    ref, m = reference_mask(views, ann, segment)
    result = propagate_masks(views.cameras, views.images, ref, m, views.points, views.seen, config, segment)
    write_masks(scene_dir, views, result, ref)
    flagged = [n for n, s in zip(views.names, result.source, strict=True) if s == "consensus"]
    if flagged:
        log.warning("masks: %d view(s) took the 3D consensus mask, check them: %s", len(flagged), flagged[:8])
    return result
