"""`load_scene`: one entry point for SPIn-NeRF folders, plain COLMAP folders and our own scenes.

Folder rules (docs/SCENES.md has the user-facing version):
- images: `images_4/` if present, else `images/`, else the first `images_N/`;
- poses: `sparse/0` (or `sparse/`, or the folder itself) with images.bin/.txt, else LLFF
  `poses_bounds.npy` (row i = view i of `views.txt`, or of the sorted image names when all are present);
- split: `views.txt` split column, else `sparse/0/test.txt`, else the first `n_test` names by sort
  order in the SPIn-NeRF layout (40) and none in a plain COLMAP folder;
- masks: `<images>/label/<name>` for training views, `<images>/test_label/out_{k+1:05d}.png` for test
  view k (SPIn-NeRF), or `masks/<name>` in a plain COLMAP folder;
- a folder with `scene.json` is one written by `save_scene` (the project's own format).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

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
from .conventions import invert_rigid, llff_to_camtoworld, scale_intrinsics
from .io import list_images, read_image, write_npy, write_png, write_text
from .masks import check_mask, dilate_mask, read_mask
from .ply import read_points_ply, write_points_ply
from .types import Camera, Scene

log = logging.getLogger(__name__)

SPINNERF_N_TEST = 40


def _image_dir(root: Path, images: str | None) -> Path:
    if images is not None:
        d = root / images
        if not d.is_dir():
            raise FileNotFoundError(f"image folder {d} not found; check the `images` argument")
        return d
    for name in ("images_4", "images"):
        if (root / name).is_dir():
            return root / name
    others = sorted(root.glob("images_*"))
    if others:
        return others[0]
    raise FileNotFoundError(f"no image folder in {root}: expected images_4/ (SPIn-NeRF) or images/ (COLMAP)")


def _read_views_txt(path: Path) -> dict[str, tuple[int, str]]:
    """views.txt -> stem -> (view index among all views, split)."""
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        t = line.split()
        out[Path(t[1]).stem] = (int(t[0]), t[2])
    return out


def _find(folder: Path, name: str) -> Path | None:
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


def _points_bounds(cam: Camera, pts: np.ndarray) -> tuple[float, float] | None:
    """Near/far from the 0.5 / 99.5 depth percentiles of points seen by the camera (as LLFF)."""
    if len(pts) == 0:
        return None
    uv, z = cam.project(pts)
    ok = cam.in_image(uv) & (z > 0)
    if ok.sum() < 10:
        return None
    return float(np.percentile(z[ok], 0.5)), float(np.percentile(z[ok], 99.5))


def load_scene(
    path: str | Path,
    *,
    images: str | None = None,
    resolution: float = 1.0,
    undistort: bool | None = None,
    n_test: int | None = None,
    mask_dilate: int = 0,
    priors: bool = True,
) -> Scene:
    """Load a scene folder (SPIn-NeRF layout, plain COLMAP, or one written by `save_scene`).

    images: image folder name inside `path` (default: images_4, images, images_N).
    resolution: further downscale (0.5 -> half size); K is scaled to match.
    undistort: undo lens distortion of COLMAP models with OpenCV. Default: yes for poses from a
      COLMAP model; no for LLFF poses_bounds.npy (SPIn-NeRF/LLFF loaders ignore it too).
    n_test: treat the first n_test views by name as test views (overrides the folder's split).
    mask_dilate: dilate training masks this many iterations with a 5x5 kernel (SPIn-NeRF uses 5).
    priors: load RGB_inpainted/ and Depth_inpainted/ when present.
    """
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"scene folder {root} not found")
    if (root / "scene.json").is_file():
        scene = _load_project(root)
        return scene.resized(resolution)

    imgdir = _image_dir(root, images)
    files = list_images(imgdir)
    if not files:
        raise FileNotFoundError(f"no .png/.jpg images in {imgdir}")
    names = [f.name for f in files]
    spinnerf = (
        (imgdir / "label").is_dir()
        or (imgdir / "test_label").is_dir()
        or (root / "poses_bounds.npy").is_file()
    )
    views = _read_views_txt(root / "views.txt") if (root / "views.txt").is_file() else None
    if views is not None:
        unknown = [n for n in names if Path(n).stem not in views]
        if unknown:
            raise ValueError(
                f"{root / 'views.txt'} does not list {unknown[:3]}; add them or remove the images"
            )
    # View index among ALL views of the capture (LLFF row; test label number).
    vindex = [views[Path(n).stem][0] if views else i for i, n in enumerate(names)]

    model_dir = find_model_dir(root)
    pb_path = root / "poses_bounds.npy"
    bounds = None
    if model_dir is not None and has_images(model_dir):
        model = read_model(model_dir)
        by_stem = {Path(k).stem: v for k, v in model.images.items()}
        poses, cam_ids = [], []
        for n in names:
            entry = model.images.get(n) or by_stem.get(Path(n).stem)
            if entry is None:
                raise ValueError(
                    f"image {imgdir / n} has no pose in the COLMAP model {model_dir}; "
                    "remove the image or re-run COLMAP mapping with it"
                )
            cam_ids.append(entry[0])
            poses.append(entry[1])
        stems = {Path(n).stem for n in names}
        extra = [k for k in model.images if Path(k).stem not in stems]
        if extra:
            log.info(
                "%s: %d posed images have no file in %s and are not loaded (e.g. %s)",
                model_dir,
                len(extra),
                imgdir,
                extra[0],
            )
        colmap_cams = model.cameras
        pts, cols = model.points, model.colors
        pose_source = f"COLMAP model {model_dir}"
        undistort = True if undistort is None else undistort
    elif pb_path.is_file():
        c2w, hwf, bnds = llff_to_camtoworld(np.load(pb_path))
        if views is None and len(c2w) != len(names):
            raise ValueError(
                f"{pb_path} has {len(c2w)} poses but {imgdir} holds {len(names)} images; with a "
                "subset of the views add views.txt (index name split) mapping names to rows"
            )
        if max(vindex) >= len(c2w):
            raise ValueError(f"view index {max(vindex)} has no pose: {pb_path} has only {len(c2w)} rows")
        if len(c2w) > len(names):
            log.info(
                "%s: %d of its %d poses have no image in %s (subset of the capture)",
                pb_path,
                len(c2w) - len(names),
                len(c2w),
                imgdir,
            )
        poses = [invert_rigid(c2w[k]) for k in vindex]
        bounds = bnds[vindex]
        if model_dir is not None:
            colmap_cams = read_cameras(model_dir)
        else:
            h, w, f = hwf[0]
            colmap_cams = {1: ColmapCamera("SIMPLE_PINHOLE", int(w), int(h), np.array([f, w / 2, h / 2]))}
        if len(colmap_cams) != 1:
            raise ValueError(f"{model_dir}: LLFF poses need a single shared camera, found {len(colmap_cams)}")
        cam_ids = [next(iter(colmap_cams))] * len(names)
        pts, cols = None, None
        pose_source = str(pb_path)
        undistort = False if undistort is None else undistort
    else:
        raise FileNotFoundError(
            f"no camera poses in {root}: expected sparse/0/images.bin (or images.txt) from COLMAP, "
            "or LLFF poses_bounds.npy; run COLMAP on the images first"
        )

    # Sparse points: model > points3D.bin/txt > points3D.ply.
    if pts is None and model_dir is not None:
        got = read_points3d(model_dir)
        if got is not None:
            pts, cols = got
        elif (model_dir / "points3D.ply").is_file():
            p, c = read_points_ply(model_dir / "points3D.ply")
            pts, cols = p.astype(np.float64), None if c is None else (c * 255).round().astype(np.uint8)
    if pts is None or len(pts) == 0:
        log.warning("%s: no sparse points (points3D.bin/.txt/.ply); scene.points is empty", root)
        pts = np.zeros((0, 3))
    colors = None if cols is None else np.asarray(cols, np.float32) / 255.0

    # Split.
    test_txt = model_dir / "test.txt" if model_dir is not None else None
    if n_test is not None:
        is_test = [i < n_test for i in range(len(names))]
        split_source = f"n_test={n_test}"
    elif views is not None:
        is_test = [views[Path(n).stem][1] == "test" for n in names]
        split_source = str(root / "views.txt")
    elif test_txt is not None and test_txt.is_file():
        stems = {Path(s.strip()).stem for s in test_txt.read_text().split() if s.strip()}
        is_test = [Path(n).stem in stems for n in names]
        split_source = str(test_txt)
    elif spinnerf:
        is_test = [i < SPINNERF_N_TEST for i in range(len(names))]
        split_source = f"SPIn-NeRF rule (first {SPINNERF_N_TEST} by name)"
    else:
        is_test = [False] * len(names)
        split_source = "plain COLMAP folder (no test views)"
    log.info("%s: %d views, poses from %s, split from %s", root, len(names), pose_source, split_source)

    cameras: list[Camera] = []
    imgs: list[np.ndarray] = []
    masks: list[np.ndarray] = []
    undistorters: dict[tuple, Undistorter | None] = {}
    label_dir, test_label_dir, masks_dir = imgdir / "label", imgdir / "test_label", root / "masks"
    n_missing_masks = 0
    view_und: list[Undistorter | None] = []
    for i, (f, V, cid) in enumerate(zip(files, poses, cam_ids, strict=True)):
        img = read_image(f)
        H, W = img.shape[:2]
        cc = colmap_cams.get(cid)
        if cc is None:
            raise ValueError(f"image {f} refers to camera {cid}, missing from {model_dir}")
        K0, dist, fisheye = pinhole_for(cc, source=str(model_dir or pb_path))
        sx, sy = W / cc.width, H / cc.height
        if abs(sx - sy) > 0.01 * sx:
            log.warning(
                "%s: image %dx%d vs camera %dx%d changes the aspect ratio", f, W, H, cc.width, cc.height
            )
        K = scale_intrinsics(K0, sx, sy)
        und = None
        if dist is not None:
            key = (cid, W, H)
            if undistort:
                if key not in undistorters:
                    undistorters[key] = Undistorter(K, dist, fisheye, W, H)
                und = undistorters[key]
            elif key not in undistorters:
                undistorters[key] = None
                log.info(
                    "%s: camera %d is %s with distortion %s; not undone (LLFF convention), "
                    "pass undistort=True to undo it",
                    root,
                    cid,
                    cc.model,
                    np.round(dist, 5),
                )
        view_und.append(und)
        if und is not None:
            img = und.image(img)
        # Mask.
        m = None
        if is_test[i]:
            mp = test_label_dir / f"out_{vindex[i] + 1:05d}.png"
            if not test_label_dir.is_dir() and masks_dir.is_dir():
                # Plain COLMAP folder with held-out views: their masks live in masks/ too.
                mp = _find(masks_dir, f.name) or masks_dir / f.name
                m = read_mask(mp, (H, W)) if mp.is_file() else None
            elif test_label_dir.is_dir():
                if not mp.is_file():
                    raise FileNotFoundError(
                        f"test mask {mp} for view {f.name} (view index {vindex[i]}) not found; "
                        "add it (name out_{index+1:05d}.png) or mark the view as train"
                    )
                m = read_mask(mp, (H, W))
        else:
            for d in (label_dir, masks_dir):
                if d.is_dir():
                    mp = _find(d, f.name)
                    if mp is None:
                        raise FileNotFoundError(
                            f"mask for training view {f} not found in {d} (expected "
                            f"{d / f.name}); add it or remove the image"
                        )
                    m = read_mask(mp, (H, W))
                    break
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
        log.warning("%s: %d views have no mask file; their masks are empty", root, n_missing_masks)

    # Per-view 2D priors shipped with the data (LaMa inpaints in SPIn-NeRF).
    prior: dict[str, dict[int, np.ndarray]] = {}
    if priors:
        for key, sub in (("rgb", "RGB_inpainted"), ("depth", "Depth_inpainted")):
            d = imgdir / sub
            if not d.is_dir():
                continue
            got: dict[int, np.ndarray] = {}
            for i, f in enumerate(files):
                if is_test[i]:
                    continue
                p = _find(d, f.name)
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

    # Extras written by the synthetic generator (ray-cast depth, object-absent/present renders).
    extras: dict[str, dict[int, np.ndarray]] = {}
    if (root / "depth").is_dir():
        extras["depth"] = {
            i: np.load(root / "depth" / (Path(n).stem + ".npy"))
            for i, n in enumerate(names)
            if (root / "depth" / (Path(n).stem + ".npy")).is_file()
        }
    for key, sub in (("object_absent", "absent"), ("object_present", "present")):
        d = imgdir / sub
        if d.is_dir():
            extras[key] = {i: read_image(p) for i, n in enumerate(names) if (p := _find(d, n))}

    pts32 = np.asarray(pts, np.float32)
    near = far = None
    if bounds is not None:
        near, far = bounds[:, 0].copy(), bounds[:, 1].copy()
    elif len(pts32):
        nf = [_points_bounds(c, pts32) for c in cameras]
        if all(b is not None for b in nf):
            near = np.array([b[0] for b in nf])
            far = np.array([b[1] for b in nf])
    scene = Scene(
        cameras=cameras,
        images=imgs,
        masks=masks,
        points=pts32,
        colors=colors,
        train_idx=[i for i in range(len(names)) if not is_test[i]],
        test_idx=[i for i in range(len(names)) if is_test[i]],
        priors=prior,
        extras=extras,
        near=near,
        far=far,
        path=root,
        meta={
            "layout": "spinnerf" if spinnerf else "colmap",
            "poses": pose_source,
            "split": split_source,
            "undistorted": bool(undistort),
            "view_index": vindex,
        },
    )
    return scene.resized(resolution)


def save_scene(scene: Scene, out_dir: str | Path) -> Path:
    """Write a scene in the project's own format: scene.json + images/ + masks/ + points3D.ply
    (+ priors/<kind>/ and extras/<kind>/ as .npy). `load_scene(out_dir)` reads it back exactly
    for cameras and masks, and to 8-bit precision for images."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    views = []
    for cam, img, m in zip(scene.cameras, scene.images, scene.masks, strict=True):
        stem = Path(cam.name).stem
        write_png(out / "images" / f"{stem}.png", img)
        write_png(out / "masks" / f"{stem}.png", m.astype(np.uint8) * 255)
        views.append(
            {
                "name": cam.name,
                "image": f"images/{stem}.png",
                "mask": f"masks/{stem}.png",
                "width": cam.width,
                "height": cam.height,
                "K": cam.K.tolist(),
                "viewmat": cam.viewmat.tolist(),
            }
        )
    for group, data in (("priors", scene.priors), ("extras", scene.extras)):
        for kind, per_view in data.items():
            for i, a in per_view.items():
                write_npy(out / group / kind / f"{Path(scene.cameras[i].name).stem}.npy", a)
    write_points_ply(out / "points3D.ply", scene.points, scene.colors)
    doc = {
        "format": "coin-cl scene",
        "version": 1,
        "views": views,
        "train_idx": scene.train_idx,
        "test_idx": scene.test_idx,
        "ref_view": scene.ref_view,
        "near": None if scene.near is None else np.asarray(scene.near).tolist(),
        "far": None if scene.far is None else np.asarray(scene.far).tolist(),
        "points": "points3D.ply",
        "meta": {k: v for k, v in scene.meta.items() if _jsonable(v)},
    }
    write_text(out / "scene.json", json.dumps(doc, indent=1))
    return out


def _jsonable(v) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False


def _load_project(root: Path) -> Scene:
    sj = root / "scene.json"
    try:
        doc = json.loads(sj.read_text())
        views = doc["views"]
    except (json.JSONDecodeError, KeyError) as exc:
        raise ValueError(f"{sj} is not a coin-cl scene file ({exc}); re-create it with save_scene") from exc
    cameras, imgs, masks = [], [], []
    for v in views:
        img = read_image(root / v["image"])
        if img.shape[:2] != (v["height"], v["width"]):
            raise ValueError(f"{root / v['image']} is not {v['width']}x{v['height']} as {sj} says")
        cameras.append(
            Camera(
                K=np.array(v["K"]),
                viewmat=np.array(v["viewmat"]),
                width=v["width"],
                height=v["height"],
                name=v["name"],
            )
        )
        imgs.append(img)
        m = read_mask(root / v["mask"], img.shape[:2])
        masks.append(check_mask(m, str(root / v["mask"])) if m.any() else m)
    pts, cols = read_points_ply(root / doc.get("points", "points3D.ply"))
    groups: dict[str, dict[str, dict[int, np.ndarray]]] = {"priors": {}, "extras": {}}
    stems = [Path(c.name).stem for c in cameras]
    for group in groups:
        gdir = root / group
        if gdir.is_dir():
            for kdir in sorted(p for p in gdir.iterdir() if p.is_dir()):
                groups[group][kdir.name] = {
                    i: np.load(kdir / f"{s}.npy")
                    for i, s in enumerate(stems)
                    if (kdir / f"{s}.npy").is_file()
                }
    return Scene(
        cameras=cameras,
        images=imgs,
        masks=masks,
        points=pts,
        colors=cols,
        train_idx=list(doc.get("train_idx", [])),
        test_idx=list(doc.get("test_idx", [])),
        priors=groups["priors"],
        extras=groups["extras"],
        ref_view=doc.get("ref_view"),
        near=None if doc.get("near") is None else np.array(doc["near"]),
        far=None if doc.get("far") is None else np.array(doc["far"]),
        path=root,
        meta={**doc.get("meta", {}), "layout": "coin-cl"},
    )
