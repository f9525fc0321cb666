"""Nerfstudio folders (`transforms.json`, as `ns-process-data` writes them) -> `Scene`.

What is read (docs/SCENES.md has the user's side; docs.nerf.studio "Data conventions" the format):
- `transforms.json`: intrinsics `fl_x fl_y cx cy w h` (+ `camera_model`, `k1 k2 k3 k4 p1 p2`) at the
  top level, any of them overridden per frame; `frames[]` with `file_path` (relative to the folder),
  `transform_matrix` (camera-to-world, OpenGL axes: x right, y up, z back) and optional `mask_path`;
  optional `test_filenames` (else `val_filenames`) for the split, `ply_file_path` for sparse points,
  `applied_transform` (3x4: COLMAP world -> this file's world) for points read from a COLMAP model.
- masks: nerfstudio's convention is 0 = pixel left out of training, non-zero = used. The object to
  inpaint is what a user left out, so coin-cl's object mask is `mask == 0` (after the usual 0/1 vs
  half-range threshold of `masks.mask_from_array`).
- sparse points: `ply_file_path` (already in the transforms' world), else `colmap/sparse/0`'s points
  mapped through `applied_transform`, else none (a warning).
Poses become OpenCV world-to-camera (`conventions.GL_FROM_CV`); no re-centring or rescaling (nerfstudio
applies its own at load time; coin-cl keeps the file's world so exports line up with it).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .colmap import Undistorter, read_points3d
from .conventions import GL_FROM_CV, invert_rigid, scale_intrinsics
from .folder import check_masks_found, near_far
from .io import read_image
from .masks import check_mask, dilate_mask, read_mask
from .ply import read_points_ply
from .types import Camera, Scene

log = logging.getLogger(__name__)

TRANSFORMS = "transforms.json"
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
# camera_model -> the OpenCV distortion vector built from transforms.json's keys, fisheye or not
DISTORTION = {
    "OPENCV": (("k1", "k2", "p1", "p2", "k3"), False),
    "OPENCV_FISHEYE": (("k1", "k2", "k3", "k4"), True),
}


def _inside(root: Path, rel: str, what: str, where: str) -> Path:
    """`root / rel`, refusing a path that leaves `root` (files come from anyone)."""
    p = (root / rel).resolve()
    if not p.is_relative_to(root.resolve()):
        raise ValueError(f"{where}: {what} {rel!r} points outside {root}; keep the files inside the folder")
    return p


def _intrinsics(doc: dict, frame: dict, where: str) -> tuple[np.ndarray, int, int, np.ndarray | None, bool]:
    """K at (w, h), w, h, distortion (None when all zero or PINHOLE), fisheye flag."""
    val = {k: frame.get(k, doc.get(k)) for k in INTRINSIC_KEYS}
    missing = [k for k, v in val.items() if v is None]
    if missing:
        raise ValueError(
            f"{where}: intrinsics {missing} missing (neither at the top of transforms.json nor in the "
            "frame); nerfstudio folders need fl_x fl_y cx cy w h"
        )
    K = np.array([[val["fl_x"], 0, val["cx"]], [0, val["fl_y"], val["cy"]], [0, 0, 1]], np.float64)
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{where}: intrinsics {val} are not finite with positive focal lengths")
    model = frame.get("camera_model", doc.get("camera_model", "OPENCV"))
    if model not in DISTORTION and model not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(
            f"{where}: camera_model {model!r} is not supported; use OPENCV, OPENCV_FISHEYE or PINHOLE"
        )
    dist, fisheye = None, False
    if model in DISTORTION:
        keys, fisheye = DISTORTION[model]
        d = np.array([float(frame.get(k, doc.get(k, 0.0)) or 0.0) for k in keys])
        dist = d if d.any() else None
    return K, int(val["w"]), int(val["h"]), dist, fisheye


def _split(doc: dict, names: list[str], n_test: int | None) -> tuple[list[bool], str]:
    if n_test is not None:
        order = sorted(range(len(names)), key=lambda i: names[i])
        test = set(order[:n_test])
        return [i in test for i in range(len(names))], f"n_test={n_test}"
    for key in ("test_filenames", "val_filenames"):
        if key in doc:
            listed = {Path(str(f)).name for f in doc[key]}
            return [Path(n).name in listed for n in names], f"transforms.json {key}"
    return [False] * len(names), "nerfstudio folder (no test views)"


def _points(root: Path, doc: dict) -> tuple[np.ndarray, np.ndarray | None, str]:
    if doc.get("ply_file_path"):
        p = _inside(root, doc["ply_file_path"], "ply_file_path", str(root / TRANSFORMS))
        pts, cols = read_points_ply(p)
        return pts, cols, str(p)
    model = root / "colmap" / "sparse" / "0"
    got = read_points3d(model) if model.is_dir() else None
    if got is None:
        log.warning("%s: no sparse points (ply_file_path or colmap/sparse/0); scene.points is empty", root)
        return np.zeros((0, 3), np.float32), None, "none"
    pts, cols = got
    if "applied_transform" in doc:
        A = np.asarray(doc["applied_transform"], np.float64)
        pts = pts @ A[:3, :3].T + A[:3, 3]
    return pts.astype(np.float32), None if cols is None else np.asarray(cols, np.float32) / 255.0, str(model)


def read_transforms(root: Path) -> dict:
    """transforms.json as a dict; unreadable JSON or no frames is one ValueError naming it."""
    path = root / TRANSFORMS
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); fix or re-run ns-process-data") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise ValueError(f"{path} has no frames list; it is not a nerfstudio transforms.json")
    return doc


def load_nerfstudio_folder(
    root: str | Path,
    *,
    undistort: bool | None = None,
    n_test: int | None = None,
    mask_dilate: int = 0,
    priors: bool = True,
) -> Scene:
    """A nerfstudio folder (module doc) at the images' resolution. `undistort` (default yes) undoes
    OPENCV / OPENCV_FISHEYE distortion with OpenCV; `priors` is accepted for `load_scene`'s sake
    (nerfstudio folders carry none)."""
    root = Path(root)
    doc = read_transforms(root)
    src = root / TRANSFORMS
    names, cameras, imgs, masks = [], [], [], []
    has_mask = False
    und_cache: dict[tuple, Undistorter] = {}
    for k, fr in enumerate(doc["frames"]):
        where = f"{src} frame {k}"
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise ValueError(f"{where}: needs file_path and transform_matrix")
        f = _inside(root, fr["file_path"], "file_path", where)
        if not f.is_file():
            raise FileNotFoundError(f"{where}: image {f} not found; fix file_path or add the image")
        c2w_gl = np.eye(4)
        M = np.asarray(fr["transform_matrix"], np.float64)
        if M.shape not in ((4, 4), (3, 4)) or not np.isfinite(M).all():
            raise ValueError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
        c2w_gl[:3] = M[:3]
        viewmat = invert_rigid(c2w_gl @ GL_FROM_CV)  # OpenGL camera axes -> OpenCV, then invert
        K, w, h, dist, fisheye = _intrinsics(doc, fr, where)
        img = read_image(f)
        H, W = img.shape[:2]
        K = scale_intrinsics(K, W / w, H / h)  # a downscaled images_N copy keeps the calibration
        und = None
        if dist is not None and undistort is not False:
            key = (tuple(K.ravel()), tuple(dist), fisheye, W, H)
            und = und_cache.setdefault(key, Undistorter(K, dist, fisheye, W, H))
            img = und.image(img)
        m = np.zeros((H, W), bool)
        if fr.get("mask_path"):
            has_mask = True
            mp = _inside(root, fr["mask_path"], "mask_path", where)
            used = read_mask(mp, (H, W))  # nerfstudio: non-zero = pixel used for training
            m = ~used
            if und is not None:
                m = und.mask(m)
            if mask_dilate:
                m = dilate_mask(m, iterations=mask_dilate)
            m = check_mask(m, source=f"{mp} (nerfstudio mask: 0 = object)")
        names.append(f.name)
        cameras.append(Camera(K=K, viewmat=viewmat, width=W, height=H, name=f.name))
        imgs.append(img)
        masks.append(m)
    if len({Path(n).stem for n in names}) != len(names):
        raise ValueError(f"{src}: two frames share an image name (stem); outputs are named by it, rename one")
    if has_mask:
        check_masks_found(root, [src], masks)
    is_test, split_source = _split(doc, names, n_test)
    pts, cols, pts_source = _points(root, doc)
    near, far = near_far(None, cameras, pts)
    n = len(names)
    log.info("%s: %d views (nerfstudio), split from %s, points from %s", root, n, split_source, pts_source)
    return Scene(
        cameras=cameras, images=imgs, masks=masks, points=pts, colors=cols,
        train_idx=[i for i in range(n) if not is_test[i]], test_idx=[i for i in range(n) if is_test[i]],
        priors={}, extras={}, near=near, far=far, path=root,
        meta={"layout": "nerfstudio", "poses": str(src), "split": split_source,
              "undistorted": bool(und_cache), "view_index": list(range(n))},
    )  # fmt: skip
