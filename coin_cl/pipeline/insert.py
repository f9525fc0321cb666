"""Insertion from one edited view (paper 1 and 5.3): stage 1's initial images when the user
gives the reference view already edited in a 2D tool (`--edited-ref IMAGE`), with no weights at all.

The paper inserts with a text prompt: SD2 inpaints every view and CLG pulls them toward the
reference's object. An edited reference carries the object for one view only; nothing here can
generate it in the others, so stage 1 lifts the edit to 3D and carries it there geometrically.
Two ways (`InsertConfig.regions`): without masks of the object in the other views (a user's one
edited photo) the object is stood on the surface under it and every view's region is derived from
its projection (`coin_cl.pipeline.insert_geometry`); with masks covering it in every view it is
lifted by their visual hull, as follows:

1. the edit E_k: the reference's mask pixels where the edited image differs from the capture
   (any channel by more than `InsertConfig.edit_tol`); an edit identical to the capture is an error;
2. its depth from the masks alone (a visual hull): along each edited pixel's ray the first point
   that projects inside the mask in at least `hull_fraction` of the training views that see it
   (at least `min_views` of them); the masks must cover where the object is to appear in every
   view, so that region of space is where it can be. Pixels whose ray meets no such point are left
   out (logged);
3. the edited pixels unprojected at that depth (the "lift" P_E, with their edited colours) are
   warped into every other training view with the engine's z-buffered point warp (CLG's
   `warp_features`), inside that view's mask; one-pixel cracks of the splat are closed;
4. I^_k = the edited image; I^_n = the capture with the warped object composited in. The working
   mask of every later stage is the footprint F_n of the object (E_k in the reference): the rest
   of the input mask is captured background, known and kept.

Later stages use the lift too: Ref-GS seeds its points with P_E (after pruning the points inside the
masks) and takes the hull depth as the reference's depth prior on E_k; CLG guides F_n toward the
reference through the Ref-GS geometry; TE-D refines. Faces of the object the reference does not see
get no colour from it (one view carries none): they stay background in I^_n.

Files (in the stage folder): images/<stem>.png (I^_n), footprints/<stem>.png (F_n),
edit/points.ply (P_E), edit/region.png (E_k), edit/depth.npy (hull camera z, NaN off E_k),
edit/views.json (per-view footprint areas).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import cv2
import numpy as np

from coin_cl.pipeline.insert_config import InsertConfig
from coin_cl.scene.io import read_image, to_uint8, write_npy, write_png, write_text

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Camera, Scene

log = logging.getLogger(__name__)


class EditLift(NamedTuple):
    """The edit lifted to 3D: points [M, 3] float32 world, colors [M, 3] float32 in [0, 1],
    region [H, W] bool (E_k, the edited reference pixels), depth [H, W] float32 camera z of E_k in
    the reference (NaN elsewhere and where the hull gave none)."""

    points: np.ndarray
    colors: np.ndarray
    region: np.ndarray
    depth: np.ndarray


def load_edited(src: Any, size: tuple[int, int], captured_size: tuple[int, int] | None = None) -> np.ndarray:
    """The edited reference as (H, W, 3) float32 in [0, 1].

    Args:
        src: a path to an image file, or an array (H, W, 3|4) uint8 / float in [0, 1] (alpha dropped).
        size: (W, H) of the reference view at the run's resolution.
        captured_size: (W, H) of the view as captured; an image of that size is resized to `size`
            the way the scene's images are (area averaging).
    Raises:
        FileNotFoundError / ValueError naming the file (or "the edited array") and what to do.
    """
    from coin_cl.scene.types import resize_image

    what = f"edited reference {src}" if isinstance(src, str | Path) else "the edited reference array"
    if isinstance(src, str | Path):
        if not Path(src).is_file():
            raise FileNotFoundError(
                f"{what} not found: give the path of the edited image of the reference view"
            )
        a = read_image(src)
    else:
        a = np.asarray(src)
        if a.dtype == np.uint8:
            a = a.astype(np.float32) / 255.0
        elif np.issubdtype(a.dtype, np.floating):
            if not np.isfinite(a).all():
                raise ValueError(f"{what} has NaN/Inf values: give finite colours in [0, 1]")
            if a.size and (a.min() < 0 or a.max() > 1):
                raise ValueError(
                    f"{what} has values in [{a.min():.3g}, {a.max():.3g}]: give floats in [0, 1] or uint8"
                )
        else:
            raise ValueError(f"{what} has dtype {a.dtype}: give uint8 or floats in [0, 1]")
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"{what} has shape {a.shape}: give an RGB image (H, W, 3)")
    a = np.ascontiguousarray(a[..., :3], dtype=np.float32)
    w, h = size
    got = (a.shape[1], a.shape[0])
    if got == (w, h):
        return a
    if captured_size is not None and got == tuple(captured_size):
        return resize_image(a, w, h)
    sizes = f"{w}x{h}" + (
        f" (or the captured {captured_size[0]}x{captured_size[1]})" if captured_size else ""
    )
    raise ValueError(
        f"{what} is {got[0]}x{got[1]} but the reference view is {sizes}: edit the captured image of that "
        "view without resizing or cropping it"
    )


def find_reference(edited: np.ndarray, scene: Scene, masks: list[np.ndarray], train: list[int],
                   ref: int | str | None, tol: float) -> int:  # fmt: skip
    """The view the edited image edits: `ref` when given (resolved by name or index), else the
    training view whose capture matches the edited image best outside its mask. Raises ValueError
    when the best match differs by more than `tol` (mean absolute, [0, 1] units)."""
    from coin_cl.pipeline.reference import choose_reference

    def diff(i: int) -> float:
        if scene.images[i].shape != edited.shape:
            return float("inf")
        out = ~np.asarray(masks[i], bool)
        return float(np.abs(scene.images[i] - edited)[out].mean()) if out.any() else float("inf")

    if ref is not None:
        k = choose_reference(masks, scene.cameras, train_idx=train, ref=ref)
        if diff(k) > tol:
            log.warning("the edited reference differs from view %s outside its mask by %.3f (> %.3f): "
                        "is it the view you edited?", scene.cameras[k].name, diff(k), tol)  # fmt: skip
        return k
    d = [diff(i) for i in train]
    k = train[int(np.argmin(d))]
    if min(d) > tol:
        raise ValueError(
            f"the edited reference matches no training view outside the masks (best {scene.cameras[k].name}, "
            f"mean difference {min(d):.3f} > {tol}): name the view it edits with --ref"
        )
    log.info("edited reference: view %d (%s), mean difference outside the mask %.4f",
             k, scene.cameras[k].name, min(d))  # fmt: skip
    return k


def edit_region(edited: np.ndarray, captured: np.ndarray, mask: np.ndarray, tol: float) -> np.ndarray:
    """E_k: mask pixels where `edited` (H, W, 3) differs from `captured` by more than `tol` in any
    channel. (H, W) bool."""
    return np.asarray(mask, bool) & (np.abs(edited - captured).max(-1) > tol)


def hull_depth(cam: Camera, region: np.ndarray, cameras: list[Camera], masks: list[np.ndarray], near: float,
               far: float, cfg: InsertConfig) -> np.ndarray:  # fmt: skip
    """Camera z of the first point along each ray of `region` (H, W) bool of `cam` that lies in the
    masks' visual hull (`InsertConfig`), searched in [near, far] (camera z); NaN where none.

    Samples are uniform in depth (a step of (far - near) / hull_samples, fine enough not to step over
    an object of that size), then refined once between the last outside and the first inside sample
    (as many samples again). (H, W) float32.
    """
    from coin_cl.gs.prune import in_masks

    ys, xs = np.nonzero(region)
    out = np.full(region.shape, np.nan, np.float32)
    if len(ys) == 0:
        return out
    uv = np.stack([xs + 0.5, ys + 0.5], 1).astype(np.float64)  # pixel centres at +0.5

    def inside(z: np.ndarray) -> np.ndarray:  # z [P, S] -> [P, S] bool
        P, S = z.shape
        pts = cam.unproject(np.repeat(uv, S, 0), z.reshape(-1))
        return in_masks(pts, cameras, masks, cfg.hull_fraction, cfg.min_views).reshape(P, S)

    S = max(2, int(cfg.hull_samples))
    z = np.linspace(near, far, S)[None].repeat(len(uv), 0)
    hit = inside(z)
    found = hit.any(1)
    first = hit.argmax(1)
    lo = np.where(first > 0, z[np.arange(len(uv)), np.maximum(first - 1, 0)], near)
    hi = z[np.arange(len(uv)), first]
    f = np.linspace(0.0, 1.0, S)[None]
    z2 = lo[:, None] + (hi - lo)[:, None] * f
    hit2 = inside(z2)
    z_hit = np.where(hit2.any(1), z2[np.arange(len(uv)), hit2.argmax(1)], hi)
    out[ys[found], xs[found]] = z_hit[found]
    return out


def depth_range(cam: Camera, points: np.ndarray) -> tuple[float, float]:
    """Search range in camera z for `hull_depth`: from 1 % of the median depth of the sparse points
    seen by `cam` to twice their 99.5th percentile (the hull stops the search well before)."""
    uv, z = cam.project(np.asarray(points, np.float64))
    ok = cam.in_image(uv) & (z > 0)
    if ok.sum() < 4:
        raise ValueError(
            f"view {cam.name}: fewer than 4 sparse points in view; cannot bound the edit's depth"
        )
    zs = z[ok]
    return 0.01 * float(np.median(zs)), 2.0 * float(np.percentile(zs, 99.5))


def check_edit(
    edited: np.ndarray, captured: np.ndarray, mask: np.ndarray, name: str, cfg: InsertConfig
) -> np.ndarray:
    """E_k (`edit_region`), or ValueError when it is empty (the edit equals the capture in the mask)."""
    region = edit_region(edited, captured, mask, cfg.edit_tol)
    if not region.any():
        raise ValueError(
            f"the edited reference equals the captured view {name} inside its mask (no pixel differs by "
            f"more than {cfg.edit_tol:.4f}): nothing to insert; paint the object inside the mask, or drop "
            "--edited-ref to remove the masked object instead"
        )
    return region


def lift_edit(edited: np.ndarray, captured: np.ndarray, k: int, scene: Scene, masks: list[np.ndarray],
              train: list[int], cfg: InsertConfig) -> EditLift:  # fmt: skip
    """Steps 1 and 2 of the module doc for reference view k. Raises ValueError when the edit is
    empty (identical to the capture inside the mask) or the hull holds none of its pixels."""
    cam = scene.cameras[k]
    region = check_edit(edited, captured, masks[k], cam.name, cfg)
    near, far = depth_range(cam, scene.points)
    depth = hull_depth(
        cam, region, [scene.cameras[i] for i in train], [masks[i] for i in train], near, far, cfg
    )
    ok = region & np.isfinite(depth)
    if not ok.any():
        raise ValueError(
            f"no edited pixel of view {cam.name} lies in the region the masks agree on (its rays meet no "
            f"point inside the masks of >= {cfg.hull_fraction:.0%} of the views that see it): give masks "
            "covering where the object should appear in every view"
        )
    if (region & ~ok).any():
        log.warning("edit: %d of %d edited pixels of view %s have no hull depth and are not lifted",
                    int((region & ~ok).sum()), int(region.sum()), cam.name)  # fmt: skip
    ys, xs = np.nonzero(ok)
    uv = np.stack([xs + 0.5, ys + 0.5], 1).astype(np.float64)
    pts = cam.unproject(uv, depth[ys, xs].astype(np.float64)).astype(np.float32)
    return EditLift(
        pts, edited[ys, xs].astype(np.float32), region, np.where(ok, depth, np.nan).astype(np.float32)
    )


def propagate(edited: np.ndarray, lift: EditLift, cam_k: Camera, cam_n: Camera, captured_n: np.ndarray,
              mask_n: np.ndarray, device: DeviceLike = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Step 3 for one view: (I^_n (H, W, 3) float32, footprint F_n (H, W) bool). The lift's points
    carry the edited colours from the reference into view n (z-buffered splat); F_n is where they
    land inside mask_n, with one-pixel cracks closed (colours there filled by Telea)."""
    from coin_cl.pipeline.reprojection import reference_in_view

    if len(lift.points) == 0 or not np.asarray(mask_n).any():
        return captured_n.astype(np.float32), np.zeros(mask_n.shape, bool)
    col, wt = reference_in_view(edited, cam_n, cam_k, lift.points, None, device)
    hit = wt > 0
    mask_n = np.asarray(mask_n, bool)
    closed = cv2.morphologyEx(hit.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    foot = closed & mask_n
    crack = foot & ~hit
    if crack.any():
        filled = cv2.inpaint(to_uint8(col), crack.astype(np.uint8), 2, cv2.INPAINT_TELEA)
        col = np.where(crack[..., None], filled.astype(np.float32) / 255.0, col)
    out = np.where(foot[..., None], col, captured_n).astype(np.float32)
    return np.clip(out, 0, 1), foot


def run_insert(scene: Scene, masks: list[np.ndarray], train: list[int], k: int, edited: np.ndarray,
               out_dir: Path, cfg: InsertConfig, device: DeviceLike = None) -> dict[str, Any]:  # fmt: skip
    """Stage 1 for insertion from an edited reference view k (module doc); writes the files the module
    doc lists into `out_dir`. Returns JSON-able figures: edited pixels, lifted points, per-view
    footprint area against the input mask area."""
    from coin_cl.scene.masks import write_mask
    from coin_cl.scene.ply import write_points_ply

    out_dir = Path(out_dir)
    if cfg.propagate and cfg.regions == "derive":
        from coin_cl.pipeline.insert_geometry import run_insert_derived

        return run_insert_derived(scene, masks, train, k, edited, out_dir, cfg, "the edited reference",
                                  device=device)  # fmt: skip
    if not cfg.propagate:
        region = edit_region(edited, scene.images[k], masks[k], cfg.edit_tol)
        for i in train:
            stem = Path(scene.cameras[i].name).stem
            write_png(out_dir / "images" / f"{stem}.png", to_uint8(edited if i == k else scene.images[i]))
            write_mask(out_dir / "footprints" / f"{stem}.png", region if i == k else np.zeros_like(region))
        return {"source": "edited reference only (naive: not propagated)", "reference": scene.cameras[k].name,
                "edited_px": int(region.sum()), "views_without_object": len(train) - 1}  # fmt: skip
    lift = lift_edit(edited, scene.images[k], k, scene, masks, train, cfg)
    write_points_ply(out_dir / "edit" / "points.ply", lift.points, lift.colors)
    write_mask(out_dir / "edit" / "region.png", lift.region)
    write_npy(out_dir / "edit" / "depth.npy", lift.depth)
    views = {}
    for i in train:
        stem = Path(scene.cameras[i].name).stem
        if i == k:
            img, foot = edited, lift.region
        else:
            img, foot = propagate(edited, lift, scene.cameras[k], scene.cameras[i], scene.images[i], masks[i],
                                  device)  # fmt: skip
        write_png(out_dir / "images" / f"{stem}.png", to_uint8(img))
        write_mask(out_dir / "footprints" / f"{stem}.png", foot)
        views[stem] = {"footprint_px": int(foot.sum()), "mask_px": int(np.asarray(masks[i]).sum())}
    write_text(out_dir / "edit" / "views.json", json.dumps(views, indent=1, sort_keys=True))
    n_empty = sum(v["footprint_px"] == 0 for v in views.values())
    log.info("insertion: %d edited pixels, %d lifted; the object lands in %d of %d training views",
             int(lift.region.sum()), len(lift.points), len(views) - n_empty, len(views))  # fmt: skip
    return {
        "source": "edited reference (lifted by the masks' visual hull, warped to the other views)",
        "reference": scene.cameras[k].name,
        "edited_px": int(lift.region.sum()),
        "lifted_points": int(len(lift.points)),
        "views_without_object": n_empty,
        "footprint_over_mask": float(
            sum(v["footprint_px"] for v in views.values()) / max(1, sum(v["mask_px"] for v in views.values()))
        ),
    }


def prepare_edit(
    edited: np.ndarray,
    scene: Scene,
    masks: list[np.ndarray],
    train: list[int],
    ref: int | str | None,
    cfg: InsertConfig,
    source: str,
) -> tuple[int, list[np.ndarray], InsertConfig]:
    """Before any stage: (the edited view k, the masks of every stage, `cfg` with `regions`
    resolved). "hull" keeps `masks` and checks the edit inside the reference's mask; "derive"
    replaces every view's mask by the region the lifted object covers there
    (`insert_geometry.derive_masks`). `source` names the edited image in errors."""
    from dataclasses import replace

    from coin_cl.pipeline.insert_geometry import derive_masks

    k = find_reference(edited, scene, masks, train, ref, cfg.ref_match_tol)
    mode = cfg.regions
    if mode == "auto":
        mode = "hull" if all(np.asarray(masks[i]).any() for i in train if i != k) else "derive"
        why = "the masks cover every other training view" if mode == "hull" else "some training views "
        log.info("insertion regions: %s (%s)", mode, why if mode == "hull" else why + "have no mask")
    cfg = replace(cfg, regions=mode)
    if mode == "hull" or not cfg.propagate:
        if not np.asarray(masks[k]).any():
            raise ValueError(
                f"{source}: view {scene.cameras[k].name} has no mask, and the hull path needs masks covering "
                "the object in every view: give them, or let the regions be derived (--insert-regions derive)"
            )
        check_edit(edited, scene.images[k], masks[k], scene.cameras[k].name, cfg)
        return k, masks, cfg
    return k, derive_masks(edited, scene, masks, k, source, cfg), cfg


def read_lift(folder: Path) -> EditLift | None:
    """The lift stage 1 wrote under `folder` (None when the run is not an insertion)."""
    from coin_cl.scene.masks import read_mask
    from coin_cl.scene.ply import read_points_ply

    d = Path(folder) / "edit"
    if not (d / "points.ply").is_file():
        return None
    pts, cols = read_points_ply(d / "points.ply")
    depth = np.load(d / "depth.npy")
    region = read_mask(d / "region.png", depth.shape)
    return EditLift(pts, cols if cols is not None else np.full_like(pts, 0.5), region, depth)
