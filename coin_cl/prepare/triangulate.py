"""Sparse points from images with known poses (COLMAP's point triangulator, through pycolmap): what
a structure-from-motion run would have given for exactly these images, without moving any camera.

Used where the images differ from the ones a capture's own model was built from (a virtual object
painted into them: `virtual_scene`), so its points describe what these images show and nothing else.

Steps (the same pycolmap calls as `sfm`): working images at `TriangulateConfig.width`; SIFT features
(one camera per image, its intrinsics replaced by the known ones); matching of each image with its
`neighbours` nearest views by pose (camera centre distance plus viewing angle; no vocabulary tree,
no file names assumed to be in capture order), with COLMAP's geometric verification; then
`pycolmap.triangulate_points` on a reconstruction that holds the known poses, refining neither poses
nor intrinsics. Only the images given take part: a point's track lists the images it came from.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..scene.io import write_png, write_text
from ..scene.types import Camera

log = logging.getLogger(__name__)


@dataclass
class TriangulateConfig:
    """Options of `triangulate_known_poses`.

    width: working width in pixels (images wider are downscaled with area averaging, K scaled).
    neighbours: each image is matched with this many nearest views by pose.
    max_features: SIFT features per image.
    num_threads: CPU threads for extraction, matching and triangulation.
    angle_weight: weight (scene units per radian of viewing-direction difference) of the angle in
        the pose distance; None: the median distance between camera centres.
    """

    width: int = 800
    neighbours: int = 10
    max_features: int = 4096
    num_threads: int = 2
    angle_weight: float | None = None


@dataclass
class Triangulated:
    """points (N, 3) float64, colors (N, 3) float32 in [0, 1], tracks: per point the names of the
    images it was triangulated from, seconds per step, n_pairs matched."""

    points: np.ndarray
    colors: np.ndarray
    tracks: list[list[str]]
    seconds: dict[str, float] = field(default_factory=dict)
    n_pairs: int = 0


def pose_neighbours(
    cameras: list[Camera], k: int, angle_weight: float | None = None
) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j: each view with its k nearest views by centre distance + angle_weight x
    angle between optical axes (radians)."""
    n = len(cameras)
    c = np.stack([cam.center for cam in cameras])
    f = np.stack([cam.camtoworld[:3, 2] for cam in cameras])
    dist = np.linalg.norm(c[:, None] - c[None], axis=2)
    ang = np.arccos(np.clip(f @ f.T, -1, 1))
    w = (
        float(np.median(dist[np.triu_indices(n, 1)]))
        if angle_weight is None and n > 1
        else angle_weight or 0.0
    )
    score = dist + w * ang
    np.fill_diagonal(score, np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(score[i])[: min(k, n - 1)]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def triangulate_known_poses(
    images: list[np.ndarray], cameras: list[Camera], work: str | Path, config: TriangulateConfig | None = None
) -> Triangulated:
    """Sparse points of `images` (per view (H, W, 3) float in [0, 1]) seen by `cameras` (same
    order, names unique), triangulated with the poses held fixed. `work` is a scratch folder this
    function creates and removes. Raises RuntimeError when fewer than 2 images or no point results."""
    import pycolmap

    cfg = config or TriangulateConfig()
    if len(images) < 2 or len(images) != len(cameras):
        raise RuntimeError(f"triangulation needs at least 2 posed images, got {len(images)}")
    work = Path(work)
    if work.exists():
        raise FileExistsError(f"scratch folder {work} exists; remove it or use another")
    imdir, db_path, out = work / "images", work / "database.db", work / "model"
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    names, cams = [], []
    try:
        for img, cam in zip(images, cameras, strict=True):
            W = min(cfg.width, cam.width)
            H = max(1, round(cam.height * W / cam.width))
            wc = cam.resized(W, H)
            if (W, H) != (cam.width, cam.height):
                img = cv2.resize(np.asarray(img, np.float32), (W, H), interpolation=cv2.INTER_AREA)
            name = f"{Path(cam.name).stem}.png"
            write_png(imdir / name, img)
            names.append(name)
            cams.append(wc)
        if len(set(names)) != len(names):
            raise ValueError("triangulate_known_poses: view names must be unique")
        seconds["images"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = cfg.num_threads
        ext.sift.max_num_features = cfg.max_features
        mode = pycolmap.CameraMode.PER_IMAGE  # one camera each: the known intrinsics differ per view
        pycolmap.extract_features(db_path, imdir, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=ext, device=pycolmap.Device.cpu)  # fmt: skip
        by_name = dict(zip(names, cams, strict=True))
        with pycolmap.Database.open(db_path) as db:
            db_images = {im.name: im for im in db.read_all_images()}
            for name, im in db_images.items():
                cam = by_name[name]
                c = db.read_camera(im.camera_id)
                c.params = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
                c.has_prior_focal_length = True
                db.update_camera(c)
        seconds["features"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        pairs = pose_neighbours(cams, cfg.neighbours, cfg.angle_weight)
        pair_file = work / "pairs.txt"
        write_text(pair_file, "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
        opts = pycolmap.FeatureMatchingOptions()
        opts.num_threads = cfg.num_threads
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(db_path, matching_options=opts, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)  # fmt: skip
        seconds["matching"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        rec = pycolmap.Reconstruction()
        with pycolmap.Database.open(db_path) as db:
            for name, im in db_images.items():
                if not rec.exists_camera(im.camera_id):
                    rec.add_camera_with_trivial_rig(db.read_camera(im.camera_id))
                cam = by_name[name]
                image = pycolmap.Image(name=name, camera_id=im.camera_id, image_id=im.image_id)
                rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cam.viewmat[:3, :4]))
        popts = pycolmap.IncrementalPipelineOptions()
        popts.num_threads = cfg.num_threads
        out.mkdir(parents=True)
        rec = pycolmap.triangulate_points(rec, db_path, imdir, out, options=popts, refine_intrinsics=False)
        seconds["triangulation"] = time.perf_counter() - t0

        id_name = {im.image_id: im.name for im in rec.images.values()}
        pts, cols, tracks = [], [], []
        for p in rec.points3D.values():
            pts.append(p.xyz)
            cols.append(np.asarray(p.color, np.float32) / 255.0)
            tracks.append(sorted({id_name[el.image_id] for el in p.track.elements}))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not pts:
        raise RuntimeError(
            f"no point could be triangulated from the {len(images)} images: they share too few matched "
            "features; use more overlapping views or a larger working width"
        )
    stem_to_view = {f"{Path(c.name).stem}.png": c.name for c in cameras}
    return Triangulated(
        points=np.asarray(pts, np.float64),
        colors=np.asarray(cols, np.float32),
        tracks=[[stem_to_view[n] for n in t] for t in tracks],
        seconds=seconds,
        n_pairs=len(pairs),
    )
