"""Image-folder layouts: SPIn-NeRF / LLFF (`load_spinnerf_folder`) and plain COLMAP
(`load_colmap_folder`). Both are an image folder plus poses (a COLMAP model, else LLFF
`poses_bounds.npy`); they differ in the default split, where masks are looked for first and what
`scene.meta["layout"]` says. docs/SCENES.md has the user-facing rules; `load_scene` picks the loader.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coin_cl.schema import SCENE_INFO, parse

from .colmap import (
    ColmapCamera,
    Undistorter,
    find_model_dir,
    has_images,
    pinhole_for,
    read_cameras,
    read_model,
    read_points3d,
)
from .conventions import check_rotation, invert_rigid, llff_to_camtoworld, scale_intrinsics
from .io import read_image
from .masks import check_mask, dilate_mask, read_mask
from .ply import read_points_ply
from .types import Camera, Scene

log = logging.getLogger(__name__)

SPINNERF_N_TEST = 40
# GScream's and FreeInpaint's SPIn-NeRF copies: training masks `lama_input/<stem>_mask.png` (the
# LaMa inputs beside them), test masks `<images>/mask_test/<stem>.png`.
LAMA_INPUT = "lama_input"
LAMA_MASK_SUFFIX = "_mask.png"


# ---------------------------------------------------------------------------------------------- the folder


@dataclass
class ImageFolder:
    """What every image-folder layout starts from: the scene root, its image folder and files,
    `views.txt` (stem -> (view index, split)) when present, each file's view index among all views
    of the capture (LLFF row; SPIn-NeRF test-label number) and the COLMAP model folder if any."""

    root: Path
    imgdir: Path
    files: list[Path]
    views: dict[str, tuple[int, str]] | None
    vindex: list[int]
    model_dir: Path | None

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.files]


# Where `coin-cl prepare` writes a scene's images when the photos themselves are in images/
# (COLMAP's layout, --out the photos' parent): the photos are never touched, so this folder wins.
PREPARED_IMAGES = "images_prepared"


def image_dir(root: Path, images: str | None) -> Path:
    """`root/images` when named, else images_prepared/, images_4/, images/, the first images_N/."""
    if images is not None:
        d = root / images
        if not d.is_dir():
            raise FileNotFoundError(f"image folder {d} not found; check the `images` argument")
        return d
    for name in (PREPARED_IMAGES, "images_4", "images"):
        if (root / name).is_dir():
            return root / name
    others = sorted(root.glob("images_*"))
    if others:
        return others[0]
    raise FileNotFoundError(f"no image folder in {root}: expected images_4/ (SPIn-NeRF) or images/ (COLMAP)")


# The largest view index views.txt may give (a capture of a million photos).
MAX_VIEW_INDEX = 1_000_000


def read_views_txt(path: Path) -> dict[str, tuple[int, str]]:
    """views.txt -> stem -> (view index among all views, split). Each line is `INDEX NAME SPLIT`
    (INDEX 0-based, SPLIT train or test); a line that is not is a ValueError naming the file and
    the line."""
    out = {}
    try:
        lines = path.read_bytes().decode("utf-8").splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file; write it as lines 'INDEX NAME train|test'") from None
    for no, line in enumerate(lines, 1):
        if line.startswith("#") or not line.strip():
            continue
        t = line.split()
        try:
            index = int(t[0])
            name, split = t[1], t[2]
        except (ValueError, IndexError):
            raise ValueError(f"{path}: line {no} is not 'INDEX NAME train|test' ({line[:60]!r}); fix or "
                             "remove that line") from None  # fmt: skip
        if not 0 <= index <= MAX_VIEW_INDEX:
            raise ValueError(f"{path}: line {no}: view index {index} is not in 0..{MAX_VIEW_INDEX}; "
                             "indices count the capture's views from 0: fix that line")  # fmt: skip
        if split not in ("train", "test"):
            raise ValueError(f"{path}: line {no}: split {split!r} is not train or test; fix that line")
        if Path(name).stem in out:
            raise ValueError(f"{path}: line {no}: {name} is listed twice; keep one line per view")
        out[Path(name).stem] = (index, split)
    return out


def read_poses_bounds(path: Path) -> np.ndarray:
    """LLFF poses_bounds.npy -> (N, 17) float64; ValueError naming the file when it is not a
    numeric (N, 17) array (never unpickled: allow_pickle stays False)."""
    try:
        pb = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not a readable .npy array ({msg}); re-create it (LLFF's "
                         "imgs2poses.py) or remove it to use sparse/0") from None  # fmt: skip
    if not isinstance(pb, np.ndarray) or pb.ndim != 2 or pb.shape[1] != 17 or pb.dtype.kind not in "fiu":
        raise ValueError(
            f"{path}: holds a {getattr(pb, 'dtype', '?')} array of shape "
            f"{getattr(pb, 'shape', '?')}, not LLFF's (N, 17) numbers; re-create it"
        )
    if len(pb) == 0:
        raise ValueError(f"{path}: holds no poses; re-create it")
    return pb.astype(np.float64)


def open_folder(root: Path, imgdir: Path, files: list[Path]) -> ImageFolder:
    """The `ImageFolder` of `root` (views.txt checked against the images)."""
    names = [f.name for f in files]
    by_stem: dict[str, list[str]] = {}
    for n in names:
        by_stem.setdefault(Path(n).stem, []).append(n)
    dup = [v for v in by_stem.values() if len(v) > 1]
    if dup:
        # masks, priors, views.txt and the outputs are matched by stem: two files would share them
        raise ValueError(
            f"{imgdir} holds images with the same name but different extensions: {dup[0]}"
            f"{f' and {len(dup) - 1} more' if len(dup) > 1 else ''}; keep one of each (rename or "
            "remove the other)"
        )
    views = read_views_txt(root / "views.txt") if (root / "views.txt").is_file() else None
    if views is not None:
        unknown = [n for n in names if Path(n).stem not in views]
        if unknown:
            raise ValueError(
                f"{root / 'views.txt'} does not list {unknown[:3]}; add them or remove the images"
            )
    vindex = [views[Path(n).stem][0] if views else i for i, n in enumerate(names)]
    return ImageFolder(root, imgdir, files, views, vindex, find_model_dir(root))


def find_file(folder: Path, name: str) -> Path | None:
    """The file for image `name` in `folder`: same name, COLMAP's `<name>.png`, else the same stem
    with .png/.jpg."""
    for p in (folder / name, folder / f"{name}.png"):
        if p.is_file():
            return p
    for ext in (".png", ".jpg", ".jpeg", ".JPG"):
        q = folder / (Path(name).stem + ext)
        if q.is_file():
            return q
    return None


# ---------------------------------------------------------------------------------------------- poses


@dataclass
class Poses:
    """World-to-camera per view, COLMAP camera ids and cameras, sparse points (None: look in the
    model folder), LLFF near/far bounds per view, and whether to undistort."""

    viewmats: list[np.ndarray]
    cam_ids: list[int]
    cameras: dict[int, ColmapCamera]
    points: np.ndarray | None
    colors: np.ndarray | None
    bounds: np.ndarray | None
    source: str
    undistort: bool


def colmap_poses(folder: ImageFolder, undistort: bool | None) -> Poses:
    """Poses of every image from the COLMAP model (by name, else by stem); undistort by default."""
    model_dir = folder.model_dir
    model = read_model(model_dir)
    by_stem = {Path(k).stem: v for k, v in model.images.items()}
    poses, cam_ids = [], []
    for n in folder.names:
        entry = model.images.get(n) or by_stem.get(Path(n).stem)
        if entry is None:
            raise ValueError(
                f"image {folder.imgdir / n} has no pose in the COLMAP model {model_dir}; "
                "remove the image or re-run COLMAP mapping with it"
            )
        cam_ids.append(entry[0])
        poses.append(entry[1])
    stems = {Path(n).stem for n in folder.names}
    extra = [k for k in model.images if Path(k).stem not in stems]
    if extra:
        log.info(
            "%s: %d posed images have no file in %s and are not loaded (e.g. %s)",
            model_dir,
            len(extra),
            folder.imgdir,
            extra[0],
        )
    return Poses(
        poses, cam_ids, model.cameras, model.points, model.colors, None, f"COLMAP model {model_dir}",
        True if undistort is None else undistort,
    )  # fmt: skip


def llff_poses(folder: ImageFolder, pb_path: Path, undistort: bool | None) -> Poses:
    """Poses from LLFF `poses_bounds.npy` (row = view index), one shared camera (the model's
    cameras file, else the file's H, W, focal); no undistortion by default (as LLFF loaders)."""
    names, vindex, model_dir = folder.names, folder.vindex, folder.model_dir
    c2w, hwf, bnds = llff_to_camtoworld(read_poses_bounds(pb_path))
    if folder.views is None and len(c2w) != len(names):
        raise ValueError(
            f"{pb_path} has {len(c2w)} poses but {folder.imgdir} holds {len(names)} images; with a "
            "subset of the views add views.txt (index name split) mapping names to rows"
        )
    if max(vindex) >= len(c2w):
        where = folder.root / "views.txt" if folder.views is not None else folder.imgdir
        raise ValueError(f"{where}: view index {max(vindex)} has no pose: {pb_path} has only {len(c2w)} rows "
                         f"(0..{len(c2w) - 1}); fix views.txt or the poses")  # fmt: skip
    if len(c2w) > len(names):
        log.info(
            "%s: %d of its %d poses have no image in %s (subset of the capture)",
            pb_path,
            len(c2w) - len(names),
            len(c2w),
            folder.imgdir,
        )
    if model_dir is not None:
        cams = read_cameras(model_dir)
    else:
        h, w, f = hwf[0]
        if not (np.isfinite([h, w]).all() and h >= 1 and w >= 1):
            raise ValueError(
                f"{pb_path}: image size {w}x{h} (row 0, columns H W) is not positive; re-create it"
            )
        cams = {1: ColmapCamera("SIMPLE_PINHOLE", int(w), int(h), np.array([f, w / 2, h / 2]))}
    if len(cams) != 1:
        raise ValueError(f"{model_dir}: LLFF poses need a single shared camera, found {len(cams)}")
    return Poses(
        [invert_rigid(c2w[k]) for k in vindex], [next(iter(cams))] * len(names), cams, None, None,
        bnds[vindex], str(pb_path), False if undistort is None else undistort,
    )  # fmt: skip


def read_poses(folder: ImageFolder, undistort: bool | None) -> Poses:
    """A COLMAP model with images wins; else LLFF poses_bounds.npy; else an error saying what to run."""
    if folder.model_dir is not None and has_images(folder.model_dir):
        return colmap_poses(folder, undistort)
    pb_path = folder.root / "poses_bounds.npy"
    if pb_path.is_file():
        return llff_poses(folder, pb_path, undistort)
    raise FileNotFoundError(
        f"no camera poses in {folder.root}: expected sparse/0/images.bin (or images.txt) from COLMAP, "
        "or LLFF poses_bounds.npy; run COLMAP on the images first"
    )


def sparse_points(folder: ImageFolder, poses: Poses) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) and colours (N, 3) float32 in [0, 1] or None: the model's, else points3D.bin/txt,
    else points3D.ply in the model folder; empty (with a warning) when there are none."""
    pts, cols, model_dir = poses.points, poses.colors, folder.model_dir
    if pts is None and model_dir is not None:
        got = read_points3d(model_dir)
        if got is not None:
            pts, cols = got
        elif (model_dir / "points3D.ply").is_file():
            p, c = read_points_ply(model_dir / "points3D.ply")
            pts, cols = p.astype(np.float64), None if c is None else (c * 255).round().astype(np.uint8)
    if pts is None or len(pts) == 0:
        log.warning("%s: no sparse points (points3D.bin/.txt/.ply); scene.points is empty", folder.root)
        pts = np.zeros((0, 3))
    return pts, None if cols is None else np.asarray(cols, np.float32) / 255.0


def points_file(folder: ImageFolder) -> str:
    """Where the scene's sparse points come from (for messages): the model folder's points3D file,
    else where one is expected."""
    d = folder.model_dir if folder.model_dir is not None else folder.root / "sparse" / "0"
    for name in ("points3D.bin", "points3D.txt", "points3D.ply"):
        if (d / name).is_file():
            return str(d / name)
    return str(d / "points3D.bin")


# ---------------------------------------------------------------------------------------------- split


# A layout's default split when neither n_test, views.txt nor sparse/0/test.txt decides.
DefaultSplit = Callable[[int], tuple[list[bool], str]]


def split_views(folder: ImageFolder, n_test: int | None, default: DefaultSplit) -> tuple[list[bool], str]:
    """Which views are test views, and where that came from: n_test (first by name), views.txt,
    sparse/0/test.txt, else the layout's default."""
    names = folder.names
    test_txt = folder.model_dir / "test.txt" if folder.model_dir is not None else None
    if n_test is not None:
        return [i < n_test for i in range(len(names))], f"n_test={n_test}"
    if folder.views is not None:
        return [folder.views[Path(n).stem][1] == "test" for n in names], str(folder.root / "views.txt")
    if test_txt is not None and test_txt.is_file():
        stems = {Path(s.strip()).stem for s in test_txt.read_text().split() if s.strip()}
        return [Path(n).stem in stems for n in names], str(test_txt)
    return default(len(names))


def spinnerf_split(n: int) -> tuple[list[bool], str]:
    """SPIn-NeRF: the first 40 views by name are the test views."""
    return [i < SPINNERF_N_TEST for i in range(n)], f"SPIn-NeRF rule (first {SPINNERF_N_TEST} by name)"


def no_test_views(n: int) -> tuple[list[bool], str]:
    """A plain COLMAP capture has no held-out views unless told."""
    return [False] * n, "plain COLMAP folder (no test views)"


# ---------------------------------------------------------------------------------------------- views


def mask_sources(folder: ImageFolder) -> list[Path]:
    """Every place this folder's masks are looked for, in order (for the error when none holds a
    non-empty mask): SPIn-NeRF's `<images>/label/` and `<images>/test_label/`, the GScream /
    FreeInpaint variant's `lama_input/<stem>_mask.png` and `<images>/mask_test/`, and `masks/`."""
    return [folder.imgdir / "label", folder.imgdir / "test_label", folder.root / LAMA_INPUT,
            folder.imgdir / "mask_test", folder.root / "masks"]  # fmt: skip


def view_mask(
    folder: ImageFolder, i: int, f: Path, is_test: bool, shape
) -> tuple[np.ndarray | None, Path | None]:
    """The mask file of view `i` read at `shape`, and its path: a test view's from
    `<images>/test_label/out_{k+1:05d}.png` (SPIn-NeRF), else `<images>/mask_test/<stem>.png`
    (GScream / FreeInpaint), else masks/ (plain COLMAP); a training view's from `<images>/label/`,
    else `lama_input/<stem>_mask.png` (GScream / FreeInpaint), else `masks/`. (None, None) when the
    folder has no mask for it."""
    label_dir, test_label_dir = folder.imgdir / "label", folder.imgdir / "test_label"
    masks_dir, mask_test_dir = folder.root / "masks", folder.imgdir / "mask_test"
    lama_dir = folder.root / LAMA_INPUT
    if is_test:
        mp = test_label_dir / f"out_{folder.vindex[i] + 1:05d}.png"
        if not test_label_dir.is_dir() and mask_test_dir.is_dir():
            mp = find_file(mask_test_dir, f.name)
            if mp is None:
                raise FileNotFoundError(
                    f"test mask for view {f.name} not found in {mask_test_dir} (expected "
                    f"{mask_test_dir / (f.stem + '.png')}); add it or mark the view as train"
                )
            return read_mask(mp, shape), mp
        if not test_label_dir.is_dir() and masks_dir.is_dir():
            # Plain COLMAP folder with held-out views: their masks live in masks/ too.
            mp = find_file(masks_dir, f.name) or masks_dir / f.name
            return (read_mask(mp, shape) if mp.is_file() else None), mp
        if test_label_dir.is_dir():
            if not mp.is_file():
                raise FileNotFoundError(
                    f"test mask {mp} for view {f.name} (view index {folder.vindex[i]}) not found; "
                    "add it (name out_{index+1:05d}.png) or mark the view as train"
                )
            return read_mask(mp, shape), mp
        return None, None
    if not label_dir.is_dir() and lama_dir.is_dir():
        mp = lama_dir / f"{f.stem}{LAMA_MASK_SUFFIX}"
        if not mp.is_file():
            raise FileNotFoundError(
                f"mask for training view {f} not found: expected {mp} (GScream / FreeInpaint layout); "
                "add it or remove the image"
            )
        return read_mask(mp, shape), mp
    for d in (label_dir, masks_dir):
        if d.is_dir():
            mp = find_file(d, f.name)
            if mp is None:
                raise FileNotFoundError(
                    f"mask for training view {f} not found in {d} (expected "
                    f"{d / f.name}); add it or remove the image"
                )
            return read_mask(mp, shape), mp
    return None, None


def check_masks_found(root: Path, where: list[Path], masks: list[np.ndarray]) -> None:
    """A folder that has masks (one of `where` exists) but whose every mask is empty is a
    ValueError naming the folder and the places looked in: every view would be left as it is and
    a run would inpaint nothing. A folder with none of them (a capture to train on) passes."""
    if any(m.any() for m in masks):
        return
    present = [d for d in where if d.exists()]
    if not present:
        return
    looked = ", ".join(str(d.relative_to(root)) if d.is_relative_to(root) else str(d) for d in where)
    found = f"; {', '.join(d.name for d in present)} exists but every mask read from it is empty"
    raise ValueError(
        f"{root}: no view has a non-empty object mask (looked in {looked}){found}; add the masks "
        "(non-zero = object) or check that the folder's layout is one docs/SCENES.md lists"
    )


# A layout's mask lookup: (folder, view i, image file, is_test, (H, W)) -> (mask or None, its path).
MaskLookup = Callable[[ImageFolder, int, Path, bool, tuple], tuple[np.ndarray | None, Path | None]]


def read_views(
    folder: ImageFolder,
    poses: Poses,
    is_test: list[bool],
    mask_dilate: int,
    mask_fn: MaskLookup | None = None,
) -> tuple[list[Camera], list[np.ndarray], list[np.ndarray], list[Undistorter | None]]:
    """Cameras (K scaled to each image's size), images and masks (undistorted where asked; masks
    found by `mask_fn`, default `view_mask`), and each view's undistorter (for the priors)."""
    mask_fn = mask_fn or view_mask
    cameras: list[Camera] = []
    imgs: list[np.ndarray] = []
    masks: list[np.ndarray] = []
    undistorters: dict[tuple, Undistorter | None] = {}
    n_missing_masks = 0
    view_und: list[Undistorter | None] = []
    source = str(folder.model_dir or folder.root / "poses_bounds.npy")
    for i, (f, V, cid) in enumerate(zip(folder.files, poses.viewmats, poses.cam_ids, strict=True)):
        img = read_image(f)
        H, W = img.shape[:2]
        cc = poses.cameras.get(cid)
        if cc is None:
            raise ValueError(f"image {f} refers to camera {cid}, missing from {folder.model_dir}")
        K0, dist, fisheye = pinhole_for(cc, source=source)
        sx, sy = W / cc.width, H / cc.height
        if abs(sx - sy) > 0.01 * sx:
            log.warning(
                "%s: image %dx%d vs camera %dx%d changes the aspect ratio", f, W, H, cc.width, cc.height
            )
        K = scale_intrinsics(K0, sx, sy)
        und = None
        if dist is not None:
            key = (cid, W, H)
            if poses.undistort:
                if key not in undistorters:
                    undistorters[key] = Undistorter(K, dist, fisheye, W, H)
                und = undistorters[key]
            elif key not in undistorters:
                undistorters[key] = None
                log.info(
                    "%s: camera %d is %s with distortion %s; not undone (LLFF convention), "
                    "pass undistort=True to undo it",
                    folder.root,
                    cid,
                    cc.model,
                    np.round(dist, 5),
                )
        view_und.append(und)
        if und is not None:
            img = und.image(img)
        m, mp = mask_fn(folder, i, f, is_test[i], (H, W))
        if m is None:
            n_missing_masks += 1
            m = np.zeros((H, W), bool)
        else:
            if und is not None:
                m = und.mask(m)
            if mask_dilate and not is_test[i]:
                m = dilate_mask(m, iterations=mask_dilate)
            m = check_mask(m, source=str(mp))
        cameras.append(Camera(K=K, viewmat=V, width=W, height=H, name=f.name))
        imgs.append(img)
        masks.append(m)
    if n_missing_masks:
        log.warning("%s: %d views have no mask file; their masks are empty", folder.root, n_missing_masks)
    return cameras, imgs, masks, view_und


def read_priors(
    folder: ImageFolder, is_test: list[bool], imgs: list[np.ndarray], view_und: list[Undistorter | None]
) -> dict[str, dict[int, np.ndarray]]:
    """Per-view 2D priors shipped with the data (LaMa inpaints in SPIn-NeRF): `<images>/RGB_inpainted`
    and `Depth_inpainted` for the training views."""
    prior: dict[str, dict[int, np.ndarray]] = {}
    for key, sub in (("rgb", "RGB_inpainted"), ("depth", "Depth_inpainted")):
        d = folder.imgdir / sub
        if not d.is_dir():
            continue
        got: dict[int, np.ndarray] = {}
        for i, f in enumerate(folder.files):
            if is_test[i]:
                continue
            p = find_file(d, f.name)
            if p is None:
                log.warning("%s: no %s prior for view %s", d, key, f.name)
                continue
            a = read_image(p)
            if a.shape[:2] != imgs[i].shape[:2]:
                raise ValueError(
                    f"prior {p} is {a.shape[1]}x{a.shape[0]} but its image is "
                    f"{imgs[i].shape[1]}x{imgs[i].shape[0]}; resize it to match"
                )
            if view_und[i] is not None:  # priors live in the same distorted pixels
                a = view_und[i].image(a)
            # The depth prior is disparity in an RGB PNG whose channels differ by a few levels.
            got[i] = a.mean(axis=2) if key == "depth" else a
        prior[key] = got
    return prior


def read_extras(folder: ImageFolder) -> dict[str, dict[int, np.ndarray]]:
    """Extras written by the synthetic generator (ray-cast depth, object-absent/present renders)."""
    root, names = folder.root, folder.names
    extras: dict[str, dict[int, np.ndarray]] = {}
    if (root / "depth").is_dir():
        extras["depth"] = {
            i: np.load(root / "depth" / (Path(n).stem + ".npy"))
            for i, n in enumerate(names)
            if (root / "depth" / (Path(n).stem + ".npy")).is_file()
        }
    for key, sub in (("object_absent", "absent"), ("object_present", "present")):
        d = folder.imgdir / sub
        if d.is_dir():
            extras[key] = {i: read_image(p) for i, n in enumerate(names) if (p := find_file(d, n))}
    return extras


def _points_bounds(cam: Camera, pts: np.ndarray) -> tuple[float, float] | None:
    """Near/far from the 0.5 / 99.5 depth percentiles of points seen by the camera (as LLFF)."""
    if len(pts) == 0:
        return None
    uv, z = cam.project(pts)
    ok = cam.in_image(uv) & (z > 0)
    if ok.sum() < 10:
        return None
    return float(np.percentile(z[ok], 0.5)), float(np.percentile(z[ok], 99.5))


def near_far(
    bounds: np.ndarray | None, cameras: list[Camera], pts32: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per-view near/far: LLFF's bounds, else from the sparse points each camera sees."""
    if bounds is not None:
        return bounds[:, 0].copy(), bounds[:, 1].copy()
    if len(pts32):
        nf = [_points_bounds(c, pts32) for c in cameras]
        if all(b is not None for b in nf):
            return np.array([b[0] for b in nf]), np.array([b[1] for b in nf])
    return None, None


def check_poses(folder: ImageFolder, poses: Poses) -> None:
    """Refuse NaN/Inf in a pose or in the LLFF bounds, and bounds that are not 0 < near < far: a
    ValueError naming the file and the view (a NaN pose would train to NaN, far later)."""
    for n, V in zip(folder.names, poses.viewmats, strict=True):
        if not np.isfinite(V).all():
            raise ValueError(
                f"the pose of image {n} in {poses.source} holds NaN or Inf; re-run COLMAP (or fix that "
                "row) or remove the image"
            )
        check_rotation(V[:3, :3], f"{poses.source}: the pose of image {n}")
    if poses.bounds is not None:
        b = np.asarray(poses.bounds, np.float64)
        bad = ~(np.isfinite(b).all(axis=1) & (b[:, 0] > 0) & (b[:, 1] > b[:, 0]))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{poses.source}: the near/far bounds of image {folder.names[k]} are {b[k].tolist()}, not "
                "finite with 0 < near < far; fix that row (LLFF's last two columns) or remove the image"
            )


# ---------------------------------------------------------------------------------------------- layouts


def _load_image_folder(
    folder: ImageFolder,
    layout: str,
    default_split: DefaultSplit,
    *,
    undistort: bool | None,
    n_test: int | None,
    mask_dilate: int,
    priors: bool,
    mask_fn: MaskLookup | None = None,
    mask_dirs: list[Path] | None = None,
) -> Scene:
    """The steps every image-folder layout shares, at the images' resolution."""
    poses = read_poses(folder, undistort)
    check_poses(folder, poses)
    pts, colors = sparse_points(folder, poses)
    is_test, split_source = split_views(folder, n_test, default_split)
    log.info(
        "%s: %d views, poses from %s, split from %s",
        folder.root,
        len(folder.files),
        poses.source,
        split_source,
    )
    cameras, imgs, masks, view_und = read_views(folder, poses, is_test, mask_dilate, mask_fn)
    check_masks_found(folder.root, mask_dirs if mask_dirs is not None else mask_sources(folder), masks)
    pts32 = np.asarray(pts, np.float32)
    near, far = near_far(poses.bounds, cameras, pts32)
    n = len(folder.files)
    return Scene(
        cameras=cameras,
        images=imgs,
        masks=masks,
        points=pts32,
        colors=colors,
        train_idx=[i for i in range(n) if not is_test[i]],
        test_idx=[i for i in range(n) if is_test[i]],
        priors=read_priors(folder, is_test, imgs, view_und) if priors else {},
        extras=read_extras(folder),
        near=near,
        far=far,
        path=folder.root,
        meta={
            "layout": layout,
            "poses": poses.source,
            "split": split_source,
            "undistorted": bool(poses.undistort),
            "view_index": folder.vindex,
            "points_file": points_file(folder),
            **masks_declared(folder.root),
        },
    )


def masks_declared(root: Path) -> dict[str, str]:
    """{"masks": value} when the folder's scene_info.json declares how its masks were made (the
    embedded synthetic rooms write "exact": every pixel outside a mask shows the background alone,
    no fringe, no shadow), else {}. Read by `CoInConfig.mask_dilate`'s default."""
    path = Path(root) / "scene_info.json"
    if not path.is_file():
        return {}
    value = parse(path, SCENE_INFO, "fix or delete the file").get("masks")
    return {"masks": str(value)} if value is not None else {}


def load_spinnerf_folder(folder: ImageFolder, **opts) -> Scene:
    """SPIn-NeRF / LLFF: `images_4/` with `label/` (training masks), `test_label/out_{k+1:05d}.png`
    (test masks), optional `RGB_inpainted/` and `Depth_inpainted/` priors; poses from sparse/0 or
    `poses_bounds.npy`; without views.txt or test.txt the first 40 views by name are the test views.
    `opts`: load_scene's undistort, n_test, mask_dilate, priors."""
    return _load_image_folder(folder, "spinnerf", spinnerf_split, **opts)


def load_colmap_folder(folder: ImageFolder, **opts) -> Scene:
    """Plain COLMAP: `images/` + `sparse/0` (+ optional `masks/<name>`, `sparse/0/test.txt` or
    views.txt); no test views unless told. `opts`: as `load_spinnerf_folder`."""
    return _load_image_folder(folder, "colmap", no_test_views, **opts)
