"""Every axis, quaternion and pixel convention the scene code meets, in one module.

The engine's convention (what `Camera` stores):
- camera axes OpenCV/COLMAP: x right, y down, z forward; `viewmat` is world-to-camera 4x4;
- pixel (x, y) covers [x, x+1) x [y, y+1), its centre at (x+0.5, y+0.5) (COLMAP), so a centred
  principal point is cx = W/2 and scaling an image by s scales fx, fy, cx, cy by s exactly;
- quaternions stored wxyz (COLMAP text files, 3DGS PLY `rot_*`).

What we convert from:
- pycolmap 4.x `Rotation3d.quat` is xyzw (Eigen order); `cam_from_world()` is a method;
- LLFF `poses_bounds.npy`: rows of 17 = 3x5 [c2w 3x4 | (H, W, f)] + (near, far), rotation columns
  ordered [down, right, backwards]; the COLMAP camera-to-world is [col1, col0, -col2 | t];
- OpenGL/NeRF-synthetic/viewer camera axes: x right, y up, z backwards;
- OpenCV image functions (undistort, remap) put pixel centres at integer coordinates, so their K has
  cx, cy half a pixel smaller than ours.
"""

from __future__ import annotations

import numpy as np

# COLMAP model name -> number of parameters; the ones `colmap_to_pinhole` can undo are marked.
COLMAP_MODEL_PARAMS: dict[str, int] = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12,
    "FOV": 5,
    "SIMPLE_RADIAL_FISHEYE": 4,
    "RADIAL_FISHEYE": 5,
    "THIN_PRISM_FISHEYE": 12,
}
# Model ids as stored in cameras.bin (COLMAP src/colmap/sensor/models.h).
COLMAP_MODEL_IDS: dict[int, str] = {i: name for i, name in enumerate(COLMAP_MODEL_PARAMS)}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)

# OpenGL <-> OpenCV camera axes (flip y and z); its own inverse.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw (pycolmap 4.x, Eigen, scipy) -> (..., 4) wxyz (COLMAP text, 3DGS PLY)."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> (..., 4) xyzw."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def quat_wxyz_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz quaternion (normalised here) -> (..., 3, 3) rotation matrix."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion wxyz with w >= 0 (Shepperd's method, stable)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def make_viewmat(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-to-camera rotation (3, 3) and translation (3,) -> (4, 4) viewmat."""
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return V


def invert_rigid(M: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform, exact up to rounding (no general inverse)."""
    R, t = M[:3, :3], M[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def look_at(eye, target, up) -> np.ndarray:
    """(4, 4) float64 world-to-camera, OpenCV axes (x right, y down, z forward), for a camera at
    `eye` looking at `target`; `up` is the world's up direction (it need not be orthogonal to the
    view direction, only not parallel to it). The one look-at of the code base."""
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    f = np.asarray(target, dtype=np.float64).reshape(3) - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, dtype=np.float64).reshape(3))
    r = r / np.linalg.norm(r)
    dn = np.cross(f, r)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([r, dn, f], axis=1)
    c2w[:3, 3] = eye
    return invert_rigid(c2w)


def llff_to_camtoworld(poses_bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LLFF `poses_bounds.npy` (N, 17) -> camtoworld (N, 4, 4) OpenCV axes, hwf (N, 3), bounds (N, 2).

    LLFF's rotation columns are [down, right, backwards]; OpenCV's are [right, down, forwards].
    """
    pb = np.asarray(poses_bounds, dtype=np.float64)
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise ValueError(f"poses_bounds must have shape (N, 17), got {pb.shape}")
    poses = pb[:, :15].reshape(-1, 3, 5)
    c2w = np.tile(np.eye(4), (len(pb), 1, 1))
    c2w[:, :3, 0] = poses[:, :, 1]
    c2w[:, :3, 1] = poses[:, :, 0]
    c2w[:, :3, 2] = -poses[:, :, 2]
    c2w[:, :3, 3] = poses[:, :, 3]
    return c2w, poses[:, :, 4].copy(), pb[:, 15:17].copy()


def camtoworld_to_llff(c2w: np.ndarray, hwf: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Inverse of `llff_to_camtoworld`: (N, 4, 4), (N, 3), (N, 2) -> poses_bounds (N, 17)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    poses = np.zeros((len(c2w), 3, 5))
    poses[:, :, 0] = c2w[:, :3, 1]
    poses[:, :, 1] = c2w[:, :3, 0]
    poses[:, :, 2] = -c2w[:, :3, 2]
    poses[:, :, 3] = c2w[:, :3, 3]
    poses[:, :, 4] = hwf
    return np.concatenate([poses.reshape(-1, 15), np.asarray(bounds, np.float64)], axis=1)


def opencv_to_opengl_camtoworld(c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) camera-to-world with OpenCV axes -> OpenGL axes (and back: it is an involution)."""
    return np.asarray(c2w, dtype=np.float64) @ GL_FROM_CV


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole K (3, 3) in the engine's pixel convention (centres at +0.5)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for an image resized by (sx, sy); exact because pixel corners, not centres, sit at 0."""
    S = np.diag([sx, sy, 1.0])
    return S @ np.asarray(K, dtype=np.float64)


def k_for_opencv(K: np.ndarray) -> np.ndarray:
    """Our K -> the K OpenCV's image functions expect (pixel centres at integers)."""
    Kc = np.array(K, dtype=np.float64)
    Kc[0, 2] -= 0.5
    Kc[1, 2] -= 0.5
    return Kc


def colmap_to_pinhole(
    model: str, params: np.ndarray, source: str = "cameras"
) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """COLMAP camera model + params -> (K (3, 3), OpenCV distortion coefficients or None, fisheye).

    Raises ValueError naming `source` for a model that cannot be converted to pinhole here.
    """
    p = np.asarray(params, dtype=np.float64)
    n = COLMAP_MODEL_PARAMS.get(model)
    if n is None or (model not in SUPPORTED_MODELS and model not in FISHEYE_MODELS):
        raise ValueError(
            f"{source}: camera model {model!r} is not supported (supported: "
            f"{', '.join(SUPPORTED_MODELS + FISHEYE_MODELS)}); undistort the images with "
            "`colmap image_undistorter` and load the undistorted folder"
        )
    if len(p) != n:
        raise ValueError(f"{source}: camera model {model} needs {n} parameters, got {len(p)}")
    if not np.isfinite(p).all():
        raise ValueError(
            f"{source}: camera model {model} has parameters {p.tolist()} with NaN or Inf; "
            "re-run COLMAP (or fix the camera's line) so that every parameter is a number"
        )
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        K = intrinsics_matrix(p[0], p[0], p[1], p[2])
    else:
        K = intrinsics_matrix(p[0], p[1], p[2], p[3])
    check_intrinsics(K, source)
    dist: np.ndarray | None
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        dist = None
    elif model == "SIMPLE_RADIAL":
        dist = np.array([p[3], 0.0, 0.0, 0.0])
    elif model == "RADIAL":
        dist = np.array([p[3], p[4], 0.0, 0.0])
    elif model == "OPENCV":
        dist = p[4:8].copy()  # k1 k2 p1 p2: same order as OpenCV
    elif model == "FULL_OPENCV":
        # COLMAP k1 k2 p1 p2 k3 k4 k5 k6 = OpenCV's rational model order.
        dist = p[4:12].copy()
    else:  # OPENCV_FISHEYE: k1..k4, OpenCV's fisheye module
        dist = p[4:8].copy()
    if dist is not None and not np.any(dist):
        dist = None
    return K, dist, model in FISHEYE_MODELS


# A loaded rotation may differ from an orthonormal matrix by this much (max abs of R^T R - I): poses
# stored as text or float32 (LLFF) are orthonormal to ~1e-6; an all-zero or scaled matrix is not.
ROTATION_TOL = 1e-3


def check_intrinsics(K: np.ndarray, source: str) -> None:
    """Refuse a (3, 3) K whose focal lengths are not finite and > 0 or whose centre is not finite:
    ValueError naming `source` and the value (a focal of 0 projects every point to the centre)."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise ValueError(
            f"{source}: focal length {fx:g}, {fy:g} (centre {cx:g}, {cy:g}) is not a positive finite "
            "number; fix the camera's intrinsics (re-run COLMAP, or correct the focal in the file)"
        )


def check_rotation(R: np.ndarray, source: str) -> None:
    """Refuse a (3, 3) rotation that is not finite, orthonormal (within ROTATION_TOL) with det +1:
    ValueError naming `source` (an all-zero rotation would collapse the camera to a point)."""
    R = np.asarray(R, dtype=np.float64)
    if not np.isfinite(R).all() or np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) <= 0:
        rows = np.array2string(R, precision=3, separator=",", max_line_width=10**6).replace("\n", "")
        raise ValueError(
            f"{source}: rotation {rows} is not a rotation matrix (finite, orthonormal, det +1); "
            "re-run COLMAP or fix that pose"
        )


def check_camera(K: np.ndarray, viewmat: np.ndarray, source: str) -> None:
    """`check_intrinsics` and `check_rotation` of a camera's K (3, 3) and viewmat (4, 4), plus a
    finite translation; errors name `source`."""
    check_intrinsics(K, source)
    V = np.asarray(viewmat, dtype=np.float64)
    check_rotation(V[:3, :3], source)
    if not np.isfinite(V[:3, 3]).all():
        raise ValueError(f"{source}: translation {V[:3, 3].tolist()} holds NaN or Inf; fix that pose")


def check_quaternion(q: np.ndarray, source: str) -> None:
    """Refuse a quaternion that is not finite or has (near) zero norm: ValueError naming `source`."""
    q = np.asarray(q, dtype=np.float64)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-8:
        raise ValueError(
            f"{source}: quaternion {q.tolist()} is zero or not finite; re-run COLMAP or fix that image's line"
        )


def _check_viewmat(V: np.ndarray, name: str) -> np.ndarray:
    V = np.asarray(V, dtype=np.float64)
    if V.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) world-to-camera matrix, got shape {V.shape}")
    if not np.all(np.isfinite(V)):
        raise ValueError(f"{name} holds NaN or Inf: a pose must be finite")
    R = V[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
        raise ValueError(f"{name}[:3, :3] is not a rotation (orthonormal with det +1 within 1e-5)")
    return V


def slerp_quat(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Unit quaternions (4,) (any order of components, the same for both) -> slerp at alpha.

    Shortest arc: q and -q are the same rotation, so q1 is negated when the dot product is
    negative (exactly opposite quaternions then coincide). When they are nearly equal
    (|dot| > 1 - 1e-12) slerp's sin(theta) in the denominator loses all precision, so normalised
    linear interpolation is used: it agrees with slerp to O(theta^3) there.
    """
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:
        q = (1.0 - alpha) * q0 + alpha * q1
        return q / np.linalg.norm(q)
    theta = np.arccos(min(d, 1.0))
    s = np.sin(theta)
    q = (np.sin((1.0 - alpha) * theta) / s) * q0 + (np.sin(alpha * theta) / s) * q1
    return q / np.linalg.norm(q)


def interpolate_pose(viewmat_k, viewmat_n, alpha: float = 0.5):
    """Intermediate camera between two world-to-camera poses (paper 4.3, the viewpoint phi).

    Args:
        viewmat_k, viewmat_n: (4, 4) world-to-camera matrices (OpenCV axes), numpy arrays or torch
            tensors; the result is float64 of the same kind (torch when `viewmat_k` is torch).
        alpha: 0 gives `viewmat_k`, 1 gives `viewmat_n` (exactly: the inputs are returned as
            float64 copies), values in between interpolate; values outside extrapolate.
    Returns:
        (4, 4) world-to-camera matrix of the intermediate camera.

    Camera CENTRES c = -R^T t are interpolated linearly, not the translation column t of the
    world-to-camera matrix: t = -R c mixes the rotation into the translation, so lerping t while
    slerping R puts the optical centre off the segment between the two cameras (for a pure
    rotation about a fixed centre it would even move the camera). The paper's "t_phi = lerp(t_k,
    t_n)" is the camera-to-world translation, i.e. the centre. Rotations are slerped on unit
    quaternions of the world-to-camera rotation (slerp commutes with inversion, so the
    camera-to-world rotation is slerped identically), on the shortest arc.
    Raises ValueError for NaN/Inf entries, a wrong shape or a non-rotation.
    """
    as_torch = False
    try:
        import torch

        as_torch = isinstance(viewmat_k, torch.Tensor)
        vk = viewmat_k.detach().cpu().numpy() if isinstance(viewmat_k, torch.Tensor) else viewmat_k
        vn = viewmat_n.detach().cpu().numpy() if isinstance(viewmat_n, torch.Tensor) else viewmat_n
    except ImportError:  # pragma: no cover - torch is a dependency
        vk, vn = viewmat_k, viewmat_n
    Vk, Vn = _check_viewmat(vk, "viewmat_k"), _check_viewmat(vn, "viewmat_n")
    a = float(alpha)
    if not np.isfinite(a):
        raise ValueError(f"alpha must be finite, got {alpha}")
    if a == 0.0:
        out = Vk.copy()
    elif a == 1.0:
        out = Vn.copy()
    else:
        ck, cn = -Vk[:3, :3].T @ Vk[:3, 3], -Vn[:3, :3].T @ Vn[:3, 3]
        q = slerp_quat(rotmat_to_quat_wxyz(Vk[:3, :3]), rotmat_to_quat_wxyz(Vn[:3, :3]), a)
        R = quat_wxyz_to_rotmat(q)
        c = (1.0 - a) * ck + a * cn
        out = make_viewmat(R, -R @ c)
    if as_torch:
        import torch

        return torch.from_numpy(out)
    return out
