"""coin-cl's own scene format: `save_scene` writes it, `load_native_folder` (through `load_scene`,
which recognises a folder by its `scene.json`) reads it back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from coin_cl.schema import SCENE, SchemaError, inside, parse

from .conventions import check_camera
from .io import read_image, write_npy, write_png, write_text
from .masks import check_mask, read_mask
from .ply import read_points_ply, write_points_ply
from .types import Camera, Scene


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
                **cam.to_json(),
                "image": f"images/{stem}.png",
                "mask": f"masks/{stem}.png",
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


def load_native_folder(root: Path) -> Scene:
    """A folder written by `save_scene` (scene.json + images/ + masks/ + points3D.ply + priors/ and
    extras/ .npy), at its stored resolution."""
    sj = root / "scene.json"
    fix = "re-create it with save_scene"
    doc = parse(sj, SCENE, fix)
    views = doc["views"]
    n = len(views)
    for key in ("train_idx", "test_idx"):
        bad = [i for i in doc[key] if i >= n]
        if bad:
            raise SchemaError(f"{sj}: {key} holds view {bad[0]}, but the file lists {n} views; {fix}")
    if doc["ref_view"] is not None and doc["ref_view"] >= n:
        raise SchemaError(f"{sj}: ref_view is {doc['ref_view']}, but the file lists {n} views; {fix}")
    for key in ("near", "far"):
        if doc[key] is not None and len(doc[key]) != n:
            raise SchemaError(f"{sj}: {key} has {len(doc[key])} values for {n} views; {fix}")
    cameras, imgs, masks = [], [], []
    for i, v in enumerate(views):
        # Every file the scene names must lie inside its folder: checked before any is opened.
        img_path = inside(root, v["image"], sj, f"views[{i}].image")
        mask_path = inside(root, v["mask"], sj, f"views[{i}].mask")
        check_camera(np.array(v["K"]), np.array(v["viewmat"]), f"{sj}: views[{i}]")
        img = read_image(img_path)
        if img.shape[:2] != (v["height"], v["width"]):
            raise ValueError(f"{img_path} is not {v['width']}x{v['height']} as {sj} says")
        cameras.append(Camera.from_json(v))
        imgs.append(img)
        m = read_mask(mask_path, img.shape[:2])
        masks.append(check_mask(m, str(mask_path)) if m.any() else m)
    pts, cols = read_points_ply(inside(root, doc["points"], sj, "points"))
    groups: dict[str, dict[str, dict[int, np.ndarray]]] = {"priors": {}, "extras": {}}
    stems = [Path(c.name).stem for c in cameras]
    for group in groups:
        gdir = root / group
        if gdir.is_dir():
            for kdir in sorted(p for p in gdir.iterdir() if p.is_dir()):
                # the arrays must lie inside the folder too (a symlinked kind folder may not lead out)
                groups[group][kdir.name] = {
                    i: np.load(inside(root, f"{group}/{kdir.name}/{s}.npy", sj, f"{group}/{kdir.name}"))
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
        meta={**doc.get("meta", {}), "layout": "coin-cl", "points_file": str(root / doc["points"])},
    )
