"""Held-out photos: posed in the prepared frame, never trained on (the object-absent ground-truth
views a benchmark scores, paper section 5; SPIn-NeRF's 40 test views).

The model is built from the training photos alone; each held-out photo is then localized in it
(`localize`): its features matched to the training photos' (the matches are already in the
database), the training photos' 3D points behind those matches give 2D-3D correspondences, and
COLMAP's absolute pose (P3P in LO-RANSAC, then refinement) places it. A held-out photo adds no
point, no track and no constraint to the training photos' poses, as COLMAP's `image_registrator`
without triangulation; hloc's localization does the same with its own matches.

The prepared folder lists them in `sparse/0/test.txt` (which `load_scene` reads as the split);
their region masks, drawn on the photos (`--holdout-masks`), are resized and undistorted with the
model's camera into `masks/<stem>.png`, beside the training masks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scene.io import IMAGE_EXTS, write_png, write_text

log = logging.getLogger(__name__)

TEST_LIST = "test.txt"
# Aspect ratios closer than this are the same camera (rounding of a resize); further apart is an error
# (the photos of one capture in `sfm`, a held-out photo's mask here).
ASPECT_TOL = 0.01
# A held-out photo needs at least this many RANSAC inliers among its 2D-3D correspondences
# (COLMAP's mapper registers an image from abs_pose_min_num_inliers = 30).
MIN_INLIERS = 30


@dataclass
class Localized:
    """A held-out photo placed in the model: its pose (world-to-camera 4x4) and how well it fits:
    correspondences found, RANSAC inliers."""

    name: str
    viewmat: np.ndarray
    n_corr: int
    n_inliers: int


def resolve_holdout(names: list[str], holdout: list[str] | tuple[str, ...]) -> list[str]:
    """The working-image names (<stem>.png) of the held-out photos, given by file name or stem.
    An unknown name, or holding out so many that fewer than 3 photos train, is a ValueError."""
    by_stem = {Path(n).stem: n for n in names}
    out = []
    for h in holdout:
        stem = Path(h).stem if Path(h).suffix in IMAGE_EXTS else h
        if stem not in by_stem:
            raise ValueError(f"--holdout {h}: no photo of that name (e.g. {names[0]}); give a photo's name")
        out.append(by_stem[stem])
    out = sorted(set(out))
    if len(names) - len(out) < 3:
        raise ValueError(
            f"holding out {len(out)} of {len(names)} photos leaves {len(names) - len(out)} to train on; "
            "structure from motion needs at least 3"
        )
    return out


def correspondences(db, rec, image_id: int, refs: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """2D keypoints (M, 2) of database image `image_id` and the 3D points (M, 3) of `rec` they
    match through the verified matches with the images `refs` of `rec` (ids; the mapped ones: one
    3D point per keypoint, the first found)."""
    kp = db.read_keypoints(image_id)[:, :2]
    got: dict[int, int] = {}
    for ref in refs:
        other = rec.images[ref]
        # (keypoint in image_id, keypoint in other): COLMAP inverts a pair stored the other way round
        m = np.asarray(db.read_two_view_geometry(image_id, other.image_id).inlier_matches)
        if len(m) == 0:
            continue
        pts2d = other.points2D
        for q, r in m:
            if q not in got and pts2d[int(r)].has_point3D():
                got[int(q)] = pts2d[int(r)].point3D_id
    q_idx = np.array(sorted(got), np.int64)
    xyz = np.array([rec.points3D[got[q]].xyz for q in q_idx], np.float64).reshape(-1, 3)
    return kp[q_idx].astype(np.float64), xyz


def localize(db_path: Path, rec, names: list[str]) -> tuple[list[Localized], dict[str, str]]:
    """Place each photo of `names` (in the database, not in `rec`) in `rec` by absolute pose and add
    it to `rec` (no points, no tracks). Returns the placed photos and name -> why for the others."""
    import pycolmap

    placed, failed = [], {}
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.random_seed = 0  # repeatable
    refs = [i for i, im in rec.images.items() if im.has_pose]  # the mapped photos, before any is added
    with pycolmap.Database.open(db_path) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        for n in names:
            im = by_name[n]
            if rec.exists_image(im.image_id):
                raise RuntimeError(f"held-out photo {n} is already in the model; remap without it")
            cam = rec.cameras[im.camera_id]
            p2, p3 = correspondences(db, rec, im.image_id, refs)
            if len(p2) < MIN_INLIERS:
                failed[n] = f"held out, but only {len(p2)} of its features match the model's points"
                continue
            res = pycolmap.estimate_and_refine_absolute_pose(p2, p3, cam, est)
            inl = 0 if res is None else int(np.sum(res["inlier_mask"]))
            if inl < MIN_INLIERS:
                failed[n] = f"held out, but its pose fits only {inl} of {len(p2)} matched points"
                continue
            cfw = res["cam_from_world"]
            image = pycolmap.Image(name=n, keypoints=np.zeros((0, 2)), camera_id=im.camera_id,
                                   image_id=im.image_id)  # fmt: skip
            rec.add_image_with_trivial_frame(image, cfw)
            V = np.eye(4)
            V[:3, :4] = cfw.matrix()
            placed.append(Localized(n, V, len(p2), inl))
    return placed, failed


def write_test_list(model_dir: Path, names: list[str]) -> None:
    """`model_dir/test.txt`: the held-out images, one a line (the split `load_scene` reads);
    removed when there are none."""
    path = Path(model_dir) / TEST_LIST
    if names:
        write_text(path, "".join(f"{n}\n" for n in names))
    else:
        path.unlink(missing_ok=True)


def read_test_list(scene_dir: str | Path) -> list[str]:
    """The held-out image names of a prepared folder (empty without `sparse/0/test.txt`)."""
    path = Path(scene_dir) / "sparse" / "0" / TEST_LIST
    return path.read_text().split() if path.is_file() else []


def write_holdout_masks(scene_dir: Path, names: list[str], masks_dir: Path, camera) -> list[str]:
    """The held-out photos' region masks from `masks_dir/<stem>.*` (drawn on the photos: the photos'
    size or any size of their aspect ratio; non-zero = region) resized to the working size and
    undistorted with the SfM `camera` (a `ColmapCamera` at the working size, before undistortion)
    into `scene_dir/masks/<stem>.png` (0/255). A missing file or another aspect ratio is an error
    naming it; returns the names written."""
    from ..scene.colmap import Undistorter, pinhole_for
    from ..scene.masks import read_mask
    from ..scene.types import resize_mask

    masks_dir = Path(masks_dir)
    if not masks_dir.is_dir():
        raise FileNotFoundError(f"--holdout-masks {masks_dir}: no such folder")
    K, dist, fisheye = pinhole_for(camera, "SfM camera")
    W, H = camera.width, camera.height
    und = Undistorter(K, dist, fisheye, W, H) if dist is not None and np.any(dist) else None
    for n in names:
        stem = Path(n).stem
        src = next((p for p in sorted(masks_dir.glob(f"{stem}.*")) if p.suffix in IMAGE_EXTS), None)
        if src is None:
            raise FileNotFoundError(f"no mask {masks_dir}/{stem}.png for held-out photo {n}; add it")
        m = read_mask(src)
        if abs(m.shape[1] / m.shape[0] - W / H) > ASPECT_TOL * W / H:
            raise ValueError(
                f"mask {src} is {m.shape[1]}x{m.shape[0]}, not the photos' aspect ratio ({W}x{H}); "
                "draw it on the photo at its size"
            )
        m = resize_mask(m, W, H)
        if und is not None:
            m = und.mask(m)
        write_png(Path(scene_dir) / "masks" / f"{stem}.png", m.astype(np.uint8) * 255)
    return list(names)
