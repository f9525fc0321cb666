"""COLMAP models: reading through pycolmap, a standalone cameras.bin/.txt reader (for folders with
no images.bin, as in the shared SPIn-NeRF scene), writing, and undistortion to pinhole."""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .conventions import (
    COLMAP_MODEL_IDS,
    COLMAP_MODEL_PARAMS,
    check_quaternion,
    colmap_to_pinhole,
    k_for_opencv,
    make_viewmat,
    quat_wxyz_to_rotmat,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
)

log = logging.getLogger(__name__)


# What to do about a COLMAP file that cannot be parsed.
REEXPORT = (
    "re-export the model with COLMAP (`colmap model_converter --output_type BIN`) or re-run `coin-cl prepare`"
)


def _text_lines(path: Path) -> list[str]:
    """The lines of a text file; ValueError naming it when it is not text."""
    try:
        return path.read_bytes().decode("utf-8").splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file; {REEXPORT}") from None


@dataclass
class ColmapCamera:
    """A COLMAP camera as stored: model name, params, size of the images it was calibrated on."""

    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapModel:
    """What we use of a COLMAP reconstruction.

    cameras: id -> ColmapCamera; images: name -> (camera id, viewmat (4, 4));
    points (N, 3) float64; colors (N, 3) uint8 or None.
    """

    cameras: dict[int, ColmapCamera]
    images: dict[str, tuple[int, np.ndarray]]
    points: np.ndarray
    colors: np.ndarray | None


def find_model_dir(root: Path) -> Path | None:
    """The folder holding cameras.{bin,txt}: root/sparse/0, root/sparse or root itself."""
    for d in (root / "sparse" / "0", root / "sparse", root):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def has_images(model_dir: Path) -> bool:
    return (model_dir / "images.bin").is_file() or (model_dir / "images.txt").is_file()


def read_cameras(model_dir: Path) -> dict[int, ColmapCamera]:
    """cameras.bin (preferred) or cameras.txt -> id -> ColmapCamera, without needing images.*."""
    binf, txtf = model_dir / "cameras.bin", model_dir / "cameras.txt"
    cams: dict[int, ColmapCamera] = {}
    if binf.is_file():
        data = binf.read_bytes()
        rec = 0
        try:
            (n,) = struct.unpack_from("<Q", data, 0)
            off = 8
            for rec in range(n):  # noqa: B007 - the record a struct.error names
                cid, mid, w, h = struct.unpack_from("<iiQQ", data, off)
                off += 24
                model = COLMAP_MODEL_IDS.get(mid)
                if model is None:
                    raise ValueError(
                        f"{binf}: unknown camera model id {mid}; re-export the model with COLMAP "
                        "(`colmap model_converter`) or convert it to PINHOLE"
                    )
                k = COLMAP_MODEL_PARAMS[model]
                params = np.array(struct.unpack_from(f"<{k}d", data, off))
                off += 8 * k
                cams[cid] = ColmapCamera(model, w, h, params)
        except struct.error:
            raise ValueError(f"{binf}: truncated or not a COLMAP cameras.bin (record {rec} of "
                             f"{len(data)} bytes); {REEXPORT}") from None  # fmt: skip
        return cams
    if txtf.is_file():
        for no, line in enumerate(_text_lines(txtf), 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            tok = line.split()
            model = tok[1] if len(tok) > 1 else ""
            if model not in COLMAP_MODEL_PARAMS:
                raise ValueError(
                    f"{txtf}: line {no}: unknown camera model {model!r}; use a COLMAP model name such as "
                    "PINHOLE or SIMPLE_RADIAL"
                )
            try:
                cams[int(tok[0])] = ColmapCamera(
                    model, int(tok[2]), int(tok[3]), np.array([float(t) for t in tok[4:]])
                )
            except (ValueError, IndexError):
                raise ValueError(f"{txtf}: line {no} is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...' "
                                 f"({line[:60]!r}); {REEXPORT}") from None  # fmt: skip
            if cams[int(tok[0])].width < 1 or cams[int(tok[0])].height < 1:
                raise ValueError(
                    f"{txtf}: line {no}: image size {tok[2]}x{tok[3]} is not positive; {REEXPORT}"
                )
        return cams
    raise FileNotFoundError(f"no cameras.bin or cameras.txt in {model_dir}")


def read_model(model_dir: Path) -> ColmapModel:
    """A full COLMAP model (binary or text) through pycolmap."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises plain exceptions with C++ messages
        raise ValueError(
            f"could not read the COLMAP model in {model_dir} ({exc}); it needs cameras, images "
            "and points3D as .bin or .txt"
        ) from exc
    cams = (
        read_cameras(model_dir)
        if (model_dir / "cameras.bin").is_file() or (model_dir / "cameras.txt").is_file()
        else {}
    )
    for cid, c in rec.cameras.items():
        if cid not in cams:
            cams[cid] = ColmapCamera(c.model.name, c.width, c.height, np.asarray(c.params))
    images: dict[str, tuple[int, np.ndarray]] = {}
    for _, im in rec.images.items():
        if not im.has_pose:
            log.warning("%s: image %s has no pose in the model; skipped", model_dir, im.name)
            continue
        pose = im.cam_from_world()
        # pycolmap 4.x quaternions are xyzw; go through our own conversion to keep one convention.
        q = quat_xyzw_to_wxyz(np.asarray(pose.rotation.quat))
        check_quaternion(q, f"{model_dir}: image {im.name}")
        images[im.name] = (im.camera_id, make_viewmat(quat_wxyz_to_rotmat(q), pose.translation))
    # Sorted by id: pycolmap's map iteration order is not the order points were written in.
    pts = [(p.xyz, p.color) for _, p in sorted(rec.points3D.items(), key=lambda kv: kv[0])]
    points = np.array([p[0] for p in pts], np.float64).reshape(-1, 3)
    colors = np.array([p[1] for p in pts], np.uint8).reshape(-1, 3)
    return ColmapModel(cams, images, points, colors if colors.any() else None)


def write_model(
    model_dir: Path,
    camera: ColmapCamera,
    names: list[str],
    viewmats: list[np.ndarray],
    points: np.ndarray,
    colors: np.ndarray,
    text: bool = False,
) -> None:
    """Write a single-camera COLMAP model through pycolmap (binary, or text when `text`).

    viewmats: per image (4, 4) world-to-camera; points (N, 3); colors (N, 3) uint8.
    """
    import pycolmap

    from .conventions import rotmat_to_quat_wxyz

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, camera.model, 1.0, camera.width, camera.height)
    cam.params = np.asarray(camera.params, np.float64)
    rec.add_camera_with_trivial_rig(cam)
    for i, (name, V) in enumerate(zip(names, viewmats, strict=True)):
        q = quat_wxyz_to_xyzw(rotmat_to_quat_wxyz(V[:3, :3]))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(q), np.asarray(V[:3, 3], np.float64))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i + 1), pose)
    for p, c in zip(np.asarray(points, np.float64), np.asarray(colors, np.uint8), strict=True):
        rec.add_point3D(p, pycolmap.Track(), c)
    model_dir.mkdir(parents=True, exist_ok=True)
    # pycolmap writes the files in place; a partial model is cleaned by writing to a temp folder.
    tmp = model_dir.parent / f".{model_dir.name}.tmp"
    tmp.mkdir(exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(tmp))
    for f in tmp.iterdir():
        f.replace(model_dir / f.name)
    tmp.rmdir()


class Undistorter:
    """Pixel maps that turn a distorted COLMAP camera's images into its pinhole twin (same K, same
    size), built once per camera and applied to images (bilinear) and masks (nearest)."""

    def __init__(self, K: np.ndarray, dist: np.ndarray, fisheye: bool, width: int, height: int):
        Kc = k_for_opencv(K)
        if fisheye:
            self.map1, self.map2 = cv2.fisheye.initUndistortRectifyMap(
                Kc, dist, np.eye(3), Kc, (width, height), cv2.CV_32FC1
            )
        else:
            self.map1, self.map2 = cv2.initUndistortRectifyMap(
                Kc, dist, None, Kc, (width, height), cv2.CV_32FC1
            )

    def image(self, img: np.ndarray) -> np.ndarray:
        """(H, W, C) float32 -> undistorted (H, W, C)."""
        return cv2.remap(img, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    def mask(self, m: np.ndarray) -> np.ndarray:
        """(H, W) bool -> undistorted (H, W) bool."""
        out = cv2.remap(m.astype(np.uint8), self.map1, self.map2, cv2.INTER_NEAREST)
        return out.astype(bool)


def pinhole_for(cam: ColmapCamera, source: str) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """K (3, 3) at the camera's calibration size, distortion, fisheye flag; errors name `source`."""
    return colmap_to_pinhole(cam.model, cam.params, source=source)


def read_points3d(model_dir: Path) -> tuple[np.ndarray, np.ndarray | None] | None:
    """points3D.bin or .txt alone (no images.* needed) -> (N, 3) float64, (N, 3) uint8 or None.

    Returns None when neither file exists.
    """
    binf, txtf = model_dir / "points3D.bin", model_dir / "points3D.txt"
    xyz: list[tuple[float, float, float]] = []
    rgb: list[tuple[int, int, int]] = []
    if binf.is_file():
        data = binf.read_bytes()
        rec = 0
        try:
            (n,) = struct.unpack_from("<Q", data, 0)
            off = 8
            for rec in range(n):  # noqa: B007 - the record a struct.error names
                vals = struct.unpack_from("<Q3d3BdQ", data, off)
                off += struct.calcsize("<Q3d3BdQ") + 8 * vals[-1]
                xyz.append(vals[1:4])
                rgb.append(vals[4:7])
        except struct.error:
            raise ValueError(f"{binf}: truncated or not a COLMAP points3D.bin (record {rec}); "
                             f"{REEXPORT}") from None  # fmt: skip
    elif txtf.is_file():
        for no, line in enumerate(_text_lines(txtf), 1):
            if line.startswith("#") or not line.strip():
                continue
            t = line.split()
            try:
                xyz.append((float(t[1]), float(t[2]), float(t[3])))
                rgb.append((int(t[4]), int(t[5]), int(t[6])))
            except (ValueError, IndexError):
                raise ValueError(f"{txtf}: line {no} is not 'POINT3D_ID X Y Z R G B ERROR TRACK...' "
                                 f"({line[:60]!r}); {REEXPORT}") from None  # fmt: skip
    else:
        return None
    src = binf if binf.is_file() else txtf
    rgb_a, xyz_a = np.array(rgb, np.int64).reshape(-1, 3), np.array(xyz, np.float64).reshape(-1, 3)
    if ((rgb_a < 0) | (rgb_a > 255)).any():
        raise ValueError(f"{src}: point colours outside 0..255; {REEXPORT}")
    if not np.isfinite(xyz_a).all():
        k = int(np.flatnonzero(~np.isfinite(xyz_a).all(axis=1))[0])
        raise ValueError(f"{src}: point {k} has a NaN or Inf coordinate; {REEXPORT}")
    colors = rgb_a.astype(np.uint8)
    return xyz_a, colors if colors.any() else None
