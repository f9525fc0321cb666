"""An embedded ground-truth scene: a small textured room with an object to remove, ray cast in numpy.

Deliberately independent of the Gaussian rasterizer: exact ray/box intersections, textures from
scikit-image's bundled photos, Lambertian shading without shadows (so the object-absent views are
exactly the object-present views with the object gone). World axes: z up, metres-ish units.

`make_synthetic` returns everything in memory; `write_synthetic` writes it in the SPIn-NeRF layout
(images_4/, label/, test_label/, sparse/0 COLMAP model, poses_bounds.npy, views.txt) plus ground truth
(`depth/<stem>.npy` camera z, `images_4/absent/` for training views, `images_4/present/` for test views).

Two tasks share the room and the cameras:
- "removal" (default): the captured views show the room with its object (the astronaut box); the
  target is the room without it.
- "insertion": the captured views show the room *without* that object, and the target is the room
  with another object (`insertion_object`, a red box) standing on the table. The masks are that
  object's footprint in every view (exact ground truth for where an insertion must appear), the
  test views hold the room *with* the object, and `paste_object` makes the "edited reference" a
  user would draw: the object's true appearance pasted into one captured view.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from .colmap import ColmapCamera, write_model
from .conventions import camtoworld_to_llff, intrinsics_matrix, look_at
from .io import write_npy, write_png, write_text
from .masks import write_mask
from .types import Camera

log = logging.getLogger(__name__)

COVERAGES = (90, 180, 360)
TASKS = ("removal", "insertion")
LIGHT = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
AMBIENT = 0.5


@dataclass
class Material:
    """A face texture: scikit-image image name, RGB tint, texels per world unit (None: stretch the
    image once over the face, like a poster)."""

    texture: str
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    density: float | None = 160.0


@dataclass
class Box:
    """An oriented box: centre (3,), half extents (3,), yaw about z (rad), six face materials in the
    order -x, +x, -y, +y, -z, +z. `inside`: seen from inside (the room)."""

    center: np.ndarray
    half: np.ndarray
    yaw: float
    faces: list[Material]
    inside: bool = False
    is_object: bool = False
    R: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, np.float64)
        self.half = np.asarray(self.half, np.float64)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        self.R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # local -> world


@lru_cache(maxsize=32)
def _texture(name: str) -> np.ndarray:
    """(H, W, 3) float32 texture from skimage.data, in [0, 1]."""
    import skimage.data

    a = getattr(skimage.data, name)()
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return a[..., :3].astype(np.float32) / 255.0


def _sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture lookup at texel coordinates (N,), (N,) -> (N, 3)."""
    H, W = tex.shape[:2]
    x = x - 0.5
    y = y - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    x0 = x0.astype(np.int64) % W
    y0 = y0.astype(np.int64) % H
    x1 = (x0 + 1) % W
    y1 = (y0 + 1) % H
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _intersect(box: Box, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays o (3,) + t d (N, 3) against a box -> t (N,) (inf on a miss), face (N,) in 0..5.

    With un-normalised d whose camera-z component is 1, t is the camera-space depth.
    """
    ol = (o - box.center) @ box.R
    dl = d @ box.R
    # Per-axis columns: numpy reductions over a length-3 last axis are several times slower.
    tmins, tmaxs = [], []
    for k in range(3):
        dk = dl[:, k]
        inv = 1.0 / np.where(np.abs(dk) < 1e-12, 1e-12, dk)
        t1 = (-box.half[k] - ol[k]) * inv
        t2 = (box.half[k] - ol[k]) * inv
        tmins.append(np.minimum(t1, t2))
        tmaxs.append(np.maximum(t1, t2))
    t_enter = np.maximum(np.maximum(tmins[0], tmins[1]), tmins[2])
    t_exit = np.minimum(np.minimum(tmaxs[0], tmaxs[1]), tmaxs[2])
    if box.inside:
        t = t_exit
        axis = np.where(tmaxs[0] == t_exit, 0, np.where(tmaxs[1] == t_exit, 1, 2))
        hit = (t_exit > 1e-9) & (t_enter <= t_exit)
        sign_pos = True
    else:
        t = t_enter
        axis = np.where(tmins[0] == t_enter, 0, np.where(tmins[1] == t_enter, 1, 2))
        hit = (t_enter <= t_exit) & (t_enter > 1e-9)
        sign_pos = False
    d_axis = np.choose(axis, (dl[:, 0], dl[:, 1], dl[:, 2]))
    # Inside, the face hit lies along the ray direction; outside, it faces the ray.
    positive = (d_axis > 0) if sign_pos else (d_axis < 0)
    return np.where(hit, t, np.inf), 2 * axis + positive


def _shade(box: Box, o: np.ndarray, d: np.ndarray, t: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Colour (N, 3) of hits on `box` (all rays given hit it)."""
    p = (o - box.center) @ box.R + t[:, None] * (d @ box.R)  # local hit points
    out = np.zeros((len(t), 3), np.float32)
    for f in range(6):
        sel = face == f
        if not sel.any():
            continue
        axis, positive = divmod(f, 2)
        a, b = [i for i in range(3) if i != axis]
        # u along the first other axis, v downwards along the second (image rows go down).
        u = p[sel, a] + box.half[a]
        v = box.half[b] - p[sel, b]
        mat = box.faces[f]
        tex = _texture(mat.texture)
        if mat.density is None:
            sx = tex.shape[1] / (2 * box.half[a])
            sy = tex.shape[0] / (2 * box.half[b])
        else:
            sx = sy = mat.density
        col = _sample(tex, u * sx, v * sy) * np.asarray(mat.tint, np.float32)
        n_local = np.zeros(3)
        n_local[axis] = 1.0 if positive else -1.0
        if box.inside:
            n_local = -n_local
        n = box.R @ n_local
        out[sel] = col * np.float32(AMBIENT + (1 - AMBIENT) * max(0.0, float(n @ LIGHT)))
    return out


def default_room(seed: int = 0) -> list[Box]:
    """The room: walls/floor/ceiling, a table, a crate on the floor, and the object on the table."""
    rng = np.random.default_rng(seed)
    M = Material
    room = Box(
        [0, 0, 1.25],
        [3.0, 3.0, 1.25],
        0.0,
        [
            M("brick", (0.95, 0.8, 0.7), 110),
            M("coffee", (1.0, 1.0, 1.0), 120),
            M("rocket", (1.0, 1.0, 1.0), 110),
            M("gravel", (0.7, 0.8, 1.0), 140),
            M("grass", (0.85, 0.7, 0.5), 120),  # floor
            M("moon", (0.95, 0.95, 1.0), 60),  # ceiling
        ],
        inside=True,
    )
    wood = M("brick", (0.75, 0.55, 0.35), 220)
    top = M("chelsea", (1.0, 0.95, 0.9), 200)
    table = Box([0, 0, 0.25], [0.8, 0.55, 0.25], 0.0, [wood, wood, wood, wood, wood, top])
    crate = Box([1.3, 0.9, 0.2], [0.2, 0.2, 0.2], 0.4, [M("colorwheel", density=None)] * 4 + [wood] * 2)
    # The object: a box with the astronaut on its sides; its pose varies with the seed.
    off = rng.uniform(-0.08, 0.08, size=2)
    yaw = float(rng.uniform(0.3, 0.9))
    poster = M("astronaut", density=None)
    obj = Box(
        [off[0], off[1], 0.5 + 0.24],
        [0.2, 0.15, 0.24],
        yaw,
        [
            poster,
            poster,
            M("immunohistochemistry", density=None),
            poster,
            M("camera", density=None),
            M("hubble_deep_field", density=None),
        ],
        is_object=True,
    )
    return [room, table, crate, obj]


def insertion_object(seed: int = 0) -> Box:
    """The object the insertion task adds: a red-tinted textured box standing on the table top
    (z = 0.5), near the table's centre, its position and yaw varying with the seed. Saturated red
    (textured: the moon photo on the sides, a checkerboard on top) is rare in the room, so where it
    lands is easy to score."""
    rng = np.random.default_rng(seed + 7)
    off = rng.uniform(-0.06, 0.06, size=2)
    # tints above 1 brighten the mid-grey moon photo into a saturated red (colours are clipped to 1)
    red = Material("moon", (1.8, 0.15, 0.1), density=None)
    top = Material("checkerboard", (1.0, 0.4, 0.1), density=None)
    return Box([off[0], off[1], 0.5 + 0.17], [0.13, 0.11, 0.17], float(rng.uniform(0.2, 0.7)),
               [red, red, red, red, top, top], is_object=True)  # fmt: skip


def room_for(task: str, seed: int = 0) -> list[Box]:
    """The boxes of a task: "removal" = `default_room` (its object is the one to remove);
    "insertion" = the room without that object plus `insertion_object` (the one to insert)."""
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    boxes = default_room(seed)
    if task == "insertion":
        boxes = [b for b in boxes if not b.is_object] + [insertion_object(seed)]
    return boxes


def paste_object(image: np.ndarray, object_image: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """An edited view as a user would make it in a 2D tool: `image` (H, W, 3) with the pixels of
    `footprint` (H, W) bool taken from `object_image` (H, W, 3), the same view rendered with the
    object. On the synthetic insertion scene this is the object's exact appearance. (H, W, 3)."""
    image, object_image = np.asarray(image), np.asarray(object_image)
    if image.shape != object_image.shape or image.shape[:2] != np.shape(footprint):
        raise ValueError(
            f"paste_object: image {image.shape}, object image {object_image.shape} and footprint "
            f"{np.shape(footprint)} must share (H, W)"
        )
    return np.where(np.asarray(footprint, bool)[..., None], object_image, image)


def arc_cameras(
    n_views: int,
    coverage: int,
    width: int,
    height: int,
    target: np.ndarray,
    seed: int,
    fov_deg: float = 60.0,
) -> list[Camera]:
    """Cameras on an arc of `coverage` degrees around `target`, looking at it; seeded jitter."""
    if coverage not in COVERAGES:
        raise ValueError(f"coverage must be one of {COVERAGES}, got {coverage}")
    rng = np.random.default_rng(seed + 1)
    if coverage == 360:
        az = -90 + 360.0 * np.arange(n_views) / n_views
    else:
        az = -90 - coverage / 2 + coverage * np.arange(n_views) / max(1, n_views - 1)
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    K = intrinsics_matrix(f, f, width / 2, height / 2)
    cams = []
    for i, a in enumerate(np.radians(az)):
        r = 2.0 + rng.uniform(-0.12, 0.12)
        h = 1.35 + rng.uniform(-0.12, 0.12)
        eye = np.array([r * np.cos(a), r * np.sin(a), h])
        tgt = target + rng.uniform(-0.04, 0.04, 3)
        vm = look_at(eye, tgt, up=(0.0, 0.0, 1.0))  # z-up world
        cams.append(Camera(K=K, viewmat=vm, width=width, height=height, name=f"{i}"))
    return cams


def _rays(cam: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and un-normalised world directions (N, 3) with camera z = 1 through (u, v)."""
    x = (u - cam.K[0, 2]) / cam.K[0, 0]
    y = (v - cam.K[1, 2]) / cam.K[1, 1]
    dc = np.stack([x, y, np.ones_like(x)], axis=1)
    c2w = cam.camtoworld
    return c2w[:3, 3], dc @ c2w[:3, :3].T


def trace(
    boxes: list[Box], cam: Camera, u: np.ndarray, v: np.ndarray, colour: bool = True
) -> dict[str, np.ndarray]:
    """Cast rays through pixel coordinates (N,) (our convention: centres at +0.5).

    Returns depth_present/depth_absent (N,) camera z, object (N,) bool (object is nearest), and,
    when `colour`, rgb_present/rgb_absent (N, 3).
    """
    o, d = _rays(cam, np.asarray(u, np.float64), np.asarray(v, np.float64))
    static = [b for b in boxes if not b.is_object]
    objs = [b for b in boxes if b.is_object]
    hits_s = [_intersect(b, o, d) for b in static]
    ts = np.stack([h[0] for h in hits_s])
    which = ts.argmin(axis=0)
    t_abs = ts.min(axis=0)
    if objs:
        hits_o = [_intersect(b, o, d) for b in objs]
        to = np.stack([h[0] for h in hits_o])
        which_o = to.argmin(axis=0)
        t_obj = to.min(axis=0)
    else:
        t_obj = np.full_like(t_abs, np.inf)
    is_obj = t_obj < t_abs
    out = {
        "depth_absent": t_abs,
        "depth_present": np.where(is_obj, t_obj, t_abs),
        "object": is_obj,
    }
    if colour:
        rgb = np.zeros((len(t_abs), 3), np.float32)
        for k, b in enumerate(static):
            sel = which == k
            if sel.any():
                rgb[sel] = _shade(b, o, d[sel], t_abs[sel], hits_s[k][1][sel])
        out["rgb_absent"] = rgb
        pres = rgb.copy()
        for k, b in enumerate(objs):
            sel = is_obj & (which_o == k)
            if sel.any():
                pres[sel] = _shade(b, o, d[sel], t_obj[sel], hits_o[k][1][sel])
        out["rgb_present"] = pres
    return out


def render_view(boxes: list[Box], cam: Camera, supersample: int = 2) -> dict[str, np.ndarray]:
    """Render one view: present/absent (H, W, 3) float32 (supersample^2 rays per pixel), mask
    (H, W) bool (any object coverage), depth_present/depth_absent (H, W) float32 at pixel centres."""
    W, H = cam.width, cam.height
    ys, xs = np.mgrid[0:H, 0:W]
    xs = xs.ravel().astype(np.float64)
    ys = ys.ravel().astype(np.float64)
    c = trace(boxes, cam, xs + 0.5, ys + 0.5, colour=False)
    acc_p = np.zeros((H * W, 3), np.float32)
    acc_a = np.zeros((H * W, 3), np.float32)
    cover = c["object"].copy()
    offs = (np.arange(supersample) + 0.5) / supersample
    for oy in offs:
        for ox in offs:
            s = trace(boxes, cam, xs + ox, ys + oy)
            acc_p += s["rgb_present"]
            acc_a += s["rgb_absent"]
            cover |= s["object"]
    n = float(supersample**2)
    absent = (acc_a / n).reshape(H, W, 3).clip(0, 1)
    present = (acc_p / n).reshape(H, W, 3).clip(0, 1)
    return {
        "present": present,
        "absent": absent,
        "mask": cover.reshape(H, W),
        "depth_present": c["depth_present"].reshape(H, W).astype(np.float32),
        "depth_absent": c["depth_absent"].reshape(H, W).astype(np.float32),
    }


@dataclass
class SyntheticScene:
    """A generated scene in memory. Per view i: cameras[i], present/absent images (H, W, 3),
    masks (H, W) bool, depth_present/depth_absent (H, W) camera z; is_test[i] marks the
    object-absent test views. points (N, 3) / colors (N, 3) in [0, 1] sampled on the surfaces the
    training views capture (none from the test views)."""

    boxes: list[Box]
    cameras: list[Camera]
    is_test: list[bool]
    present: list[np.ndarray]
    absent: list[np.ndarray]
    masks: list[np.ndarray]
    depth_present: list[np.ndarray]
    depth_absent: list[np.ndarray]
    points: np.ndarray
    colors: np.ndarray
    params: dict


def make_synthetic(
    coverage: int = 180,
    n_views: int = 40,
    width: int = 256,
    height: int = 192,
    seed: int = 0,
    n_points: int = 20000,
    supersample: int = 2,
    task: str = "removal",
) -> SyntheticScene:
    """Generate the room scene. Every 4th camera along the arc (offset 2) is a test view; views are
    ordered test first, as in SPIn-NeRF, so `cameras[:n_test]` are the test views.

    task: "removal" or "insertion" (module doc). The cameras aim at the removal object's centre
    in both, so the two tasks share one rig for a seed. In either task `present` is the room with
    the task's object and `masks` its footprint; the "SfM" points come from what is captured."""
    if n_views < 4:
        raise ValueError(f"n_views must be at least 4 (1 test view per 4), got {n_views}")
    rng = np.random.default_rng(seed)
    boxes = room_for(task, seed)
    aim = next(b for b in default_room(seed) if b.is_object).center
    cams = arc_cameras(n_views, coverage, width, height, aim, seed)
    test_pos = [i for i in range(n_views) if i % 4 == 2]
    order = test_pos + [i for i in range(n_views) if i % 4 != 2]
    cams = [cams[i] for i in order]
    is_test = [i < len(test_pos) for i in range(n_views)]
    for j, c in enumerate(cams):
        c.name = f"view_{j:03d}.png"
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("present", "absent", "mask", "dp", "da")}
    pts, cols = [], []
    n_train = n_views - len(test_pos)
    per_view = int(np.ceil(n_points / n_train))
    for j, cam in enumerate(cams):
        r = render_view(boxes, cam, supersample)
        out["present"].append(r["present"])
        out["absent"].append(r["absent"])
        out["mask"].append(r["mask"])
        out["dp"].append(r["depth_present"])
        out["da"].append(r["depth_absent"])
        # "SfM" points: what the training views capture (removal: the room with the object;
        # insertion: the room without it). The test views are ground truth the method never sees,
        # so no point comes from them: points on surfaces only a test view sees would hand a
        # method the truth behind the object (they would flatter masked reconstruction).
        if is_test[j]:
            continue
        key = "absent" if task == "insertion" else "present"
        depth = r[f"depth_{key}"]
        flat = rng.choice(width * height, size=per_view, replace=per_view > width * height)
        yy, xx = np.divmod(flat, width)
        uv = np.stack([xx + 0.5, yy + 0.5], axis=1)
        pts.append(cam.unproject(uv, depth[yy, xx].astype(np.float64)))
        cols.append(r[key][yy, xx])
    points = np.concatenate(pts)[:n_points]
    colors = np.concatenate(cols)[:n_points].clip(0, 1)
    return SyntheticScene(
        boxes=boxes,
        cameras=cams,
        is_test=is_test,
        present=out["present"],
        absent=out["absent"],
        masks=out["mask"],
        depth_present=out["dp"],
        depth_absent=out["da"],
        points=points,
        colors=colors,
        params={
            "coverage": coverage,
            "n_views": n_views,
            "width": width,
            "height": height,
            "seed": seed,
            "n_points": n_points,
            "supersample": supersample,
            "task": task,
        },
    )


def write_synthetic(out_dir: str | Path, scene: SyntheticScene | None = None, **kwargs) -> Path:
    """Write a synthetic scene (made with `make_synthetic(**kwargs)` unless given) in the SPIn-NeRF
    layout that `load_scene` reads. Returns the folder.

    Training views hold what is captured (removal: the room with the object; insertion: without),
    test views the target (removal: without; insertion: with), `depth/` the camera z of whichever
    image the view holds, and `images_4/absent/` / `images_4/present/` the other one."""
    s = scene if scene is not None else make_synthetic(**kwargs)
    insertion = s.params.get("task") == "insertion"
    root = Path(out_dir)
    imgdir = root / "images_4"
    n_test = sum(s.is_test)
    lines = ["# index  name  split  included_here  mask_file"]
    for j, cam in enumerate(s.cameras):
        stem = Path(cam.name).stem
        shows_object = s.is_test[j] == insertion  # removal: train views; insertion: test views
        img, other, depth = (
            (s.present[j], "absent", s.depth_present[j])
            if shows_object
            else (s.absent[j], "present", s.depth_absent[j])
        )
        write_png(imgdir / cam.name, img)
        write_png(imgdir / other / cam.name, s.absent[j] if shows_object else s.present[j])
        write_npy(root / "depth" / f"{stem}.npy", depth)
        if s.is_test[j]:
            mask_rel = f"images_4/test_label/out_{j + 1:05d}.png"
        else:
            mask_rel = f"images_4/label/{cam.name}"
        write_mask(root / mask_rel, s.masks[j])
        lines.append(f"{j:3d}  {cam.name}  {'test' if s.is_test[j] else 'train'}  yes  {mask_rel}")
    write_text(root / "views.txt", "\n".join(lines) + "\n")
    cam0 = s.cameras[0]
    K = cam0.K
    model = ColmapCamera("PINHOLE", cam0.width, cam0.height, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    c8 = (s.colors * 255 + 0.5).astype(np.uint8)
    write_model(
        root / "sparse" / "0",
        model,
        [c.name for c in s.cameras],
        [c.viewmat for c in s.cameras],
        s.points,
        c8,
    )
    write_text(root / "sparse" / "0" / "test.txt", "\n".join(c.name for c in s.cameras[:n_test]) + "\n")
    # LLFF poses too, so the poses_bounds.npy path can be checked against the COLMAP one.
    depths = [
        s.depth_present[j] if s.is_test[j] == insertion else s.depth_absent[j] for j in range(len(s.cameras))
    ]
    bounds = np.array([[np.percentile(d, 0.5), np.percentile(d, 99.5)] for d in depths])
    hwf = np.array([[cam0.height, cam0.width, K[0, 0]]] * len(s.cameras))
    pb = camtoworld_to_llff(np.stack([c.camtoworld for c in s.cameras]), hwf, bounds)
    write_npy(root / "poses_bounds.npy", pb)
    info = {
        **s.params,
        "generator": "coin_cl.scene.synthetic",
        "n_test": n_test,
        "object_center": s.boxes[-1].center.tolist(),
        # A mask is any object coverage of the supersampled rays and nothing casts a shadow, so
        # every pixel outside it shows the background alone: the pipeline keeps such masks as
        # given (`CoInConfig.mask_dilate`).
        "masks": "exact",
    }
    write_text(root / "scene_info.json", json.dumps(info, indent=1))
    log.info("synthetic scene (%d views, %d test) written to %s", len(s.cameras), n_test, root)
    return root


def truly_unseen(s: SyntheticScene, views: list[int], depth_tol: float = 0.02) -> list[np.ndarray]:
    """Ground truth for 3D-first refined masks: per view n of `views`, the mask pixels whose surface
    point in the scene *without* the object (ray-cast depth) no other view of `views` sees outside
    its own mask (visible there: in the image, in front, and at the depth that view's capture shows,
    within `depth_tol` relative). These are what a removal must still invent; the rest of the mask
    is seen elsewhere. (H, W) bool per view, in the order of `views`."""
    out = []
    for n in views:
        cam = s.cameras[n]
        ys, xs = np.nonzero(s.masks[n])
        uv = np.stack([xs + 0.5, ys + 0.5], 1)
        pts = cam.unproject(uv, s.depth_absent[n][ys, xs].astype(np.float64))
        seen = np.zeros(len(pts), bool)
        for m in views:
            if m == n:
                continue
            c = s.cameras[m]
            uvm, z = c.project(pts)
            ok = c.in_image(uvm) & (z > 0)
            px = np.zeros((len(pts), 2), np.int64)
            px[ok] = np.floor(uvm[ok]).astype(np.int64)
            d = s.depth_present[m][px[:, 1], px[:, 0]]
            vis = ok & (np.abs(z - d) <= depth_tol * d) & ~s.masks[m][px[:, 1], px[:, 0]]
            seen |= vis
        u = np.zeros_like(s.masks[n])
        u[ys[~seen], xs[~seen]] = True
        out.append(u)
    return out
