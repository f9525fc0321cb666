"""Structure from motion for a folder of photos (the data preparation that CoIn, paper section 4,
takes as given: posed views of one scene), through pycolmap.

Steps, each resumable (a second run skips what is already on disk):
  1. working images: every photo downscaled to `SfmConfig.width` (never upscaled), one size for all;
  2. SIFT features (one shared camera, SIMPLE_RADIAL by default);
  3. matching: exhaustive up to `exhaustive_max` images, sequential by file name beyond (no
     vocabulary tree, so no file to download);
  4. incremental mapping; the largest model is kept;
  5. undistortion to PINHOLE at the same size and focal length (COLMAP's undistorter with its scale
     pinned to 1), written as `SCENE/images/` + `SCENE/sparse/0/` (the plain COLMAP layout of
     docs/SCENES.md, which `coin_cl.load_scene` reads);
  6. a report (`SCENE/prepare_report.json` and `.txt`): registered images, mean reprojection error,
     and each dropped image with the reason.
Held-out photos (`holdout`, e.g. object-absent ground-truth views) get features and matches but
stay out of the mapping; they are localized in the finished model (`holdout.localize`) and written
as test views (`sparse/0/test.txt`).

Scratch files live in `SCENE/.prepare/` (working images, database, raw models). The photos are
only read: when they are `SCENE/images/` (COLMAP's layout), the undistorted images go to
`SCENE/images_prepared/` instead (`scene_images`; `load_scene` looks there first).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..atomic import copy_file
from ..scene.folder import PREPARED_IMAGES
from ..scene.io import IMAGE_EXTS, read_image, write_png, write_text
from .holdout import ASPECT_TOL, localize, resolve_holdout, write_test_list
from .sfm_report import SfmReport, why_dropped, write_report

log = logging.getLogger(__name__)

WORK = ".prepare"


@dataclass
class SfmConfig:
    """Options of `run_sfm`.

    width: working width in pixels; wider photos are downscaled (area averaging), narrower ones are
        kept (never upscaled). Every working image gets the size of the first photo scaled to it.
    exhaustive_max: up to this many images every pair is matched; beyond, each image is matched
        with its `sequential_overlap` neighbours by file name (photos taken in order).
    camera_model: COLMAP model fitted to the shared camera before undistortion.
    max_features: SIFT features per image.
    num_threads: CPU threads for extraction, matching and mapping.
    seed: random seed of the mapper (RANSAC), for repeatable runs.
    """

    width: int = 1008
    exhaustive_max: int = 80
    sequential_overlap: int = 15
    camera_model: str = "SIMPLE_RADIAL"
    max_features: int = 8192
    num_threads: int = 2
    seed: int = 0


# ------------------------------------------------------------------------------------- input checks


def list_photos(photos_dir: str | Path) -> list[Path]:
    """The photos of a folder, sorted by name; clear errors for a missing or unusable folder."""
    d = Path(photos_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"photo folder {d} not found; give a folder of .jpg/.png photos")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix in IMAGE_EXTS)
    if not files:
        raise ValueError(f"photo folder {d} has no .jpg/.png images; put the photos directly in it")
    if len(files) < 3:
        raise ValueError(
            f"photo folder {d} has {len(files)} image(s); structure from motion needs at least 3 "
            "overlapping photos of the scene (20-100 is typical)"
        )
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise ValueError(f"{p} and {stems[p.stem]} share a name; rename one (outputs are <name>.png)")
        stems[p.stem] = p
    return files


def working_size(sizes: list[tuple[int, int]], names: list[str], width: int) -> tuple[int, int]:
    """(W, H) every photo is resized to: the first photo's aspect at min(width, its width).

    Photos of other sizes with the same aspect ratio (within 1 %) are resized to it; another aspect
    (a portrait among landscapes, a crop) is an error naming the photo.
    """
    if width < 16:
        raise ValueError(f"working width {width} is too small; use at least 16 (about 1000 is typical)")
    w0, h0 = sizes[0]
    for (w, h), n in zip(sizes, names, strict=True):
        if abs(w / h - w0 / h0) > ASPECT_TOL * (w0 / h0):
            raise ValueError(
                f"photo {n} is {w}x{h} but {names[0]} is {w0}x{h0}: mixed aspect ratios; rotate or "
                "crop the photos to one aspect ratio, or remove the odd ones"
            )
    W = min(width, w0)
    return W, max(1, round(h0 * W / w0))


def image_size(path: Path) -> tuple[int, int]:
    """(W, H) of an image file without decoding all of it where the format allows."""
    import imageio.v3 as iio

    try:
        shape = iio.improps(path).shape
    except Exception as exc:  # imageio raises plugin-specific errors
        raise ValueError(f"photo {path} could not be read ({exc}); remove it or re-save it") from exc
    return int(shape[1]), int(shape[0])


def scene_images(scene: Path, photos_dir: Path) -> Path:
    """The folder of the scene's undistorted images: SCENE/images, or SCENE/images_prepared when
    the photos are SCENE/images."""
    if os.path.realpath(scene / "images") == os.path.realpath(photos_dir):
        return scene / PREPARED_IMAGES
    return scene / "images"


# Everything prepare writes or replaces inside SCENE (besides its images folder and its reports).
OWN_FOLDERS = (WORK, "sparse", "masks", ".masks.tmp", PREPARED_IMAGES)


def check_photos_outside_outputs(photos_dir: Path, scene: Path) -> None:
    """Refuse photos that lie in a folder prepare writes or replaces (they would be deleted)."""
    real = Path(os.path.realpath(photos_dir))
    own = [scene / d for d in OWN_FOLDERS]
    if scene_images(scene, photos_dir) == scene / "images":
        own.append(scene / "images")
    for d in own:
        if real.is_relative_to(os.path.realpath(d)):
            raise ValueError(
                f"the photos in {photos_dir} lie in {d}, which prepare writes: move the photos "
                "elsewhere or choose another --out"
            )


# ------------------------------------------------------------------------------------------- steps


def _prepare_images(photos: list[Path], imdir: Path, size: tuple[int, int]) -> list[str]:
    """Working images as <stem>.png at `size` (kept when already there at that size)."""
    imdir.mkdir(parents=True, exist_ok=True)
    names = []
    for p in tqdm(photos, desc="prepare: resize", unit="img", leave=False):
        dst = imdir / f"{p.stem}.png"
        names.append(dst.name)
        if dst.is_file() and image_size(dst) == size:
            continue
        if p.suffix.lower() == ".png" and image_size(p) == size:
            copy_file(p, dst)  # already a PNG of the working size
            continue
        img = read_image(p)
        if (img.shape[1], img.shape[0]) != size:
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        write_png(dst, img)
    return names


def _extract(db_path: Path, imdir: Path, names: list[str], cfg: SfmConfig) -> bool:
    """Features into the database; False when a complete database for these images was reused."""
    import pycolmap

    if db_path.is_file():
        with pycolmap.Database.open(db_path) as db:
            have = {im.name for im in db.read_all_images()}
        if have == set(names):
            log.info("features: reusing %s", db_path)
            return False
        db_path.unlink()  # another set of images: start the database afresh
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = cfg.num_threads
    ext.sift.max_num_features = cfg.max_features
    tmp = db_path.with_suffix(".tmp.db")
    tmp.unlink(missing_ok=True)
    pycolmap.extract_features(
        tmp,
        imdir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=ext,
        device=pycolmap.Device.cpu,
    )
    tmp.replace(db_path)  # the database is complete only once it has its final name
    return True


def image_pairs(names: list[str], method: str, overlap: int) -> list[tuple[str, str]]:
    """Pairs to match: every pair ("exhaustive"), or each image with its `overlap` successors by
    name plus successors at distances 2^k beyond ("sequential", as COLMAP's quadratic overlap)."""
    n = len(names)
    if method == "exhaustive":
        return [(names[i], names[j]) for i in range(n) for j in range(i + 1, n)]
    steps = sorted(set(range(1, overlap + 1)) | {2**k for k in range(int(np.log2(max(n, 2))) + 1)})
    return [(names[i], names[i + d]) for i in range(n) for d in steps if i + d < n]


def _match(db_path: Path, names: list[str], cfg: SfmConfig, marker: Path, work: Path) -> str:
    """Match in chunks of pairs (progress per chunk; COLMAP skips pairs already in the database,
    so an interrupted run resumes where it stopped)."""
    import pycolmap

    method = "exhaustive" if len(names) <= cfg.exhaustive_max else "sequential"
    if marker.is_file() and marker.read_text().strip() == method:
        log.info("matching: reusing the %s matches in %s", method, db_path)
        return method
    pairs = image_pairs(names, method, cfg.sequential_overlap)
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = cfg.num_threads
    chunk = max(16, len(pairs) // 40)
    pair_file = work / "pairs.txt"
    with tqdm(total=len(pairs), desc=f"prepare: {method} matching", unit="pair", leave=False) as bar:
        for k in range(0, len(pairs), chunk):
            part = pairs[k : k + chunk]
            write_text(pair_file, "".join(f"{a} {b}\n" for a, b in part))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(db_path, matching_options=opts, pairing_options=pairing,
                                       device=pycolmap.Device.cpu)  # fmt: skip
            bar.update(len(part))
    pair_file.unlink(missing_ok=True)
    write_text(marker, method)
    return method


def _map(db_path: Path, imdir: Path, out: Path, cfg: SfmConfig, train: list[str],
         held: list[str]) -> tuple[Path, dict[str, int]]:  # fmt: skip
    """The largest model of the `train` images in out/best (the `held` ones left out); also name ->
    size of the other models' images."""
    import pycolmap

    best = out / "best"
    others_file, held_file = out / "others.json", out / "holdout.json"
    same_held = (json.loads(held_file.read_text()) if held_file.is_file() else []) == held
    if (best / "images.bin").is_file() and others_file.is_file() and same_held:
        log.info("mapping: reusing %s", best)
        return best, json.loads(others_file.read_text())
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.min_model_size = 3
    if held:
        opts.image_names = train  # the held-out photos are localized afterwards, never mapped
    n_images = len(train)
    with tqdm(total=n_images, desc="prepare: mapping", unit="img", leave=False) as bar:
        recs = pycolmap.incremental_mapping(db_path, imdir, out / "raw", opts,
                                            initial_image_pair_callback=lambda: bar.update(2),
                                            next_image_callback=lambda: bar.update(1))  # fmt: skip
    if not recs:
        raise RuntimeError(
            f"no model could be built from the photos in {imdir}: no pair of photos shares enough "
            "matched features; take overlapping photos (each point seen from 3 or more)"
        )
    order = sorted(recs, key=lambda k: -recs[k].num_reg_images())
    others = {}
    for k in order[1:]:
        for im in recs[k].images.values():
            others[im.name] = recs[k].num_reg_images()
    tmp = out / "best.tmp"
    tmp.mkdir()
    recs[order[0]].write_binary(str(tmp))
    write_text(others_file, json.dumps(others))
    write_text(held_file, json.dumps(held))
    tmp.rename(best)
    return best, others


def _undistort(model: Path, imdir: Path, work: Path, scene: Path, images: Path) -> None:
    """PINHOLE images and model at the same size and focal length into `images` (scene_images),
    scene/sparse/0."""
    import pycolmap

    und = work / "undistorted"
    shutil.rmtree(und, ignore_errors=True)
    opts = pycolmap.UndistortCameraOptions()
    opts.min_scale = opts.max_scale = 1.0  # same size and focal: a mask drawn on a photo still fits
    pycolmap.undistort_images(und, model, imdir, undistort_options=opts)
    for sub, dst in (("images", images), ("sparse", scene / "sparse" / "0")):
        shutil.rmtree(dst, ignore_errors=True)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(und / sub), str(dst))
    shutil.rmtree(und, ignore_errors=True)


# ------------------------------------------------------------------------------------------- driver


def run_sfm(photos_dir: str | Path, scene_dir: str | Path, config: SfmConfig | None = None,
            holdout: list[str] | tuple[str, ...] = ()) -> SfmReport:  # fmt: skip
    """Photos -> a posed scene folder (plain COLMAP layout, PINHOLE) and its report.

    holdout: photos (file names or stems) kept out of the mapping, localized in the model of the
    others and written as test views (`sparse/0/test.txt`; module docstring).
    Resumes: each step whose output exists in `scene_dir/.prepare` is skipped. Raises ValueError /
    FileNotFoundError on unusable input and RuntimeError when no model can be built.
    """
    import pycolmap

    old = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = 1  # COLMAP's per-image INFO lines drown the progress bar
    try:
        check_photos_outside_outputs(Path(photos_dir), Path(scene_dir))
        images = scene_images(Path(scene_dir), Path(photos_dir))
        return _run_steps(list_photos(photos_dir), Path(scene_dir), images, config or SfmConfig(),
                          tuple(holdout))  # fmt: skip
    finally:
        pycolmap.logging.minloglevel = old


def _run_steps(photos: list[Path], scene: Path, images: Path, cfg: SfmConfig,
               holdout: tuple[str, ...]) -> SfmReport:  # fmt: skip
    import pycolmap

    work = scene / WORK
    held = resolve_holdout([f"{p.stem}.png" for p in photos], holdout) if holdout else []
    sizes = [image_size(p) for p in photos]
    W, H = working_size(sizes, [p.name for p in photos], cfg.width)
    work.mkdir(parents=True, exist_ok=True)
    imdir, db_path = work / "images", work / "database.db"
    size_file = work / "size.txt"
    if size_file.is_file() and size_file.read_text().strip() != f"{W}x{H}":
        # another working size: features, matches and models of the earlier run do not apply
        log.info("working size changed to %dx%d; starting the SfM afresh", W, H)
        db_path.unlink(missing_ok=True)
        (work / "matched.txt").unlink(missing_ok=True)
        for d in (work / "sparse", scene / "sparse" / "0"):
            shutil.rmtree(d, ignore_errors=True)
    write_text(size_file, f"{W}x{H}")
    seconds: dict[str, float] = {}
    steps = tqdm(total=5, desc="prepare", unit="step")

    def step(name: str) -> None:
        seconds[name] = time.perf_counter() - t0
        steps.set_postfix_str(f"{name} done in {seconds[name]:.1f} s")
        steps.update(1)

    t0 = time.perf_counter()
    steps.set_description("prepare: resize")
    names = _prepare_images(photos, imdir, (W, H))
    step("resize")
    t0 = time.perf_counter()
    steps.set_description("prepare: features")
    if _extract(db_path, imdir, names, cfg):
        # new features: matches, models and outputs of an earlier run are stale
        (work / "matched.txt").unlink(missing_ok=True)
        shutil.rmtree(work / "sparse", ignore_errors=True)
    step("features")
    t0 = time.perf_counter()
    steps.set_description("prepare: matching")
    method = _match(db_path, names, cfg, work / "matched.txt", work)
    step("matching")
    t0 = time.perf_counter()
    steps.set_description("prepare: mapping")
    mapped_before = (work / "sparse" / "best" / "images.bin").is_file()
    train = [n for n in names if n not in held]
    model, others = _map(db_path, imdir, work / "sparse", cfg, train, held)
    if not mapped_before:
        shutil.rmtree(scene / "sparse" / "0", ignore_errors=True)
    step("mapping")
    t0 = time.perf_counter()
    steps.set_description("prepare: undistort")
    rec = pycolmap.Reconstruction(str(model))
    registered = sorted(im.name for im in rec.images.values() if im.has_pose)
    error, n_points = float(rec.compute_mean_reprojection_error()), int(rec.num_points3D())
    placed, failed = localize(db_path, rec, held) if held else ([], {})
    if held:  # the model to undistort: the training photos' plus the localized ones (no points added)
        model = work / "sparse" / "localized"
        shutil.rmtree(model, ignore_errors=True)
        model.mkdir()
        rec.write_binary(str(model))
    test_list = scene / "sparse" / "0" / "test.txt"
    listed = test_list.read_text().split() if test_list.is_file() else []
    if (not (scene / "sparse" / "0" / "images.bin").is_file() or not images.is_dir()
            or listed != [p.name for p in placed]):  # fmt: skip
        _undistort(model, imdir, work, scene, images)
    write_test_list(scene / "sparse" / "0", [p.name for p in placed])
    _drop_stale_images(images, set(registered) | {p.name for p in placed})
    step("undistort")
    steps.close()
    report = SfmReport(
        n_photos=len(names),
        registered=registered,
        dropped={**why_dropped(db_path, train, set(registered), others), **failed},
        mean_reproj_error=error,
        n_points=n_points,
        matching=method,
        width=W,
        height=H,
        photo_width=sizes[0][0],
        photo_height=sizes[0][1],
        seconds=seconds,
        held_out={p.name: {"matched_points": p.n_corr, "inliers": p.n_inliers} for p in placed},
    )
    write_report(scene, report)
    if len(registered) < 3:
        why = scene / "prepare_report.txt"
        raise RuntimeError(f"only {len(registered)} of {len(names)} photos could be posed; see {why}")
    return report


def _drop_stale_images(imdir: Path, keep: set[str]) -> None:
    """Images of a previous run that the model no longer poses would be an error for the loader."""
    for p in imdir.iterdir():
        if p.is_file() and p.name not in keep:
            p.unlink()
