"""Conventions: quaternion orders, LLFF axes, OpenGL flips, intrinsics scaling, camera models."""

import numpy as np
import pycolmap
import pytest

from coin_cl.scene import Camera
from coin_cl.scene.conventions import (
    camtoworld_to_llff,
    colmap_to_pinhole,
    intrinsics_matrix,
    invert_rigid,
    llff_to_camtoworld,
    opencv_to_opengl_camtoworld,
    quat_wxyz_to_rotmat,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotmat_to_quat_wxyz,
    scale_intrinsics,
)


def _random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q


def test_quaternion_round_trip_and_orthonormal():
    rng = np.random.default_rng(1)
    for q in _random_quats(rng, 50):
        R = quat_wxyz_to_rotmat(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(rotmat_to_quat_wxyz(R), q, atol=1e-10)
    np.testing.assert_array_equal(quat_xyzw_to_wxyz([1, 2, 3, 4]), [4, 1, 2, 3])
    np.testing.assert_array_equal(quat_wxyz_to_xyzw([4, 1, 2, 3]), [1, 2, 3, 4])


def test_pycolmap_quaternion_is_xyzw():
    # pycolmap 4.x stores xyzw: our wxyz quaternion, reordered, must give the same matrix.
    rng = np.random.default_rng(2)
    for q in _random_quats(rng, 10):
        rot = pycolmap.Rotation3d(quat_wxyz_to_xyzw(q))
        np.testing.assert_allclose(rot.matrix(), quat_wxyz_to_rotmat(q), atol=1e-12)


def test_llff_axes_and_round_trip():
    # One LLFF pose with rotation columns [down, right, backwards] of a camera looking along +y.
    down, right, back = np.array([0, 0, -1.0]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0])
    row = np.concatenate([np.stack([down, right, back, [1, 2, 3], [480, 640, 500]], 1).ravel(), [1, 9]])
    c2w, hwf, bounds = llff_to_camtoworld(row[None])
    # OpenCV camera: x right, y down, z forward.
    np.testing.assert_allclose(c2w[0, :3, 0], right)
    np.testing.assert_allclose(c2w[0, :3, 1], down)
    np.testing.assert_allclose(c2w[0, :3, 2], -back)
    np.testing.assert_allclose(c2w[0, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(hwf[0], [480, 640, 500])
    np.testing.assert_allclose(bounds[0], [1, 9])
    np.testing.assert_allclose(camtoworld_to_llff(c2w, hwf, bounds), row[None])


def test_opengl_flip_is_involution_and_flips_axes():
    rng = np.random.default_rng(3)
    c2w = np.eye(4)
    c2w[:3, :3] = quat_wxyz_to_rotmat(_random_quats(rng, 1)[0])
    gl = opencv_to_opengl_camtoworld(c2w)
    np.testing.assert_allclose(gl[:3, 1], -c2w[:3, 1])
    np.testing.assert_allclose(gl[:3, 2], -c2w[:3, 2])
    np.testing.assert_allclose(opencv_to_opengl_camtoworld(gl), c2w)


def test_scaled_intrinsics_map_pixel_corners():
    # With centres at +0.5, the image's corner (0, 0) and far corner (W, H) scale exactly.
    K = intrinsics_matrix(500.0, 510.0, 320.0, 240.0)
    K2 = scale_intrinsics(K, 0.5, 0.25)
    cam = Camera(K=K, viewmat=np.eye(4), width=640, height=480)
    cam2 = cam.resized(320, 120)
    np.testing.assert_allclose(cam2.K, K2)
    pts = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]])
    uv, _ = cam.project(pts)
    uv2, _ = cam2.project(pts)
    np.testing.assert_allclose(uv2, uv * [0.5, 0.25])


def test_camera_project_unproject_and_torch():
    rng = np.random.default_rng(4)
    V = np.eye(4)
    V[:3, :3] = quat_wxyz_to_rotmat(_random_quats(rng, 1)[0])
    V[:3, 3] = rng.normal(size=3)
    cam = Camera(K=intrinsics_matrix(300, 300, 64, 48), viewmat=V, width=128, height=96)
    uv = rng.uniform(0, 96, size=(20, 2))
    d = rng.uniform(1, 5, size=20)
    X = cam.unproject(uv, d)
    uv2, z = cam.project(X)
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(z, d, atol=1e-9)
    np.testing.assert_allclose(cam.camtoworld, invert_rigid(V), atol=1e-12)
    vm, K = cam.torch()
    assert vm.dtype.is_floating_point and vm.shape == (4, 4) and str(vm.dtype) == "torch.float32"
    np.testing.assert_allclose(K.numpy(), cam.K, rtol=1e-6)


def test_colmap_models_to_pinhole():
    K, dist, fish = colmap_to_pinhole("SIMPLE_RADIAL", [100, 50, 40, 0.1])
    np.testing.assert_allclose(K, intrinsics_matrix(100, 100, 50, 40))
    np.testing.assert_allclose(dist, [0.1, 0, 0, 0])
    assert not fish
    K, dist, _ = colmap_to_pinhole("PINHOLE", [100, 110, 50, 40])
    assert dist is None and K[1, 1] == 110
    _, dist, _ = colmap_to_pinhole("FULL_OPENCV", np.arange(1, 13, dtype=float))
    np.testing.assert_allclose(dist, np.arange(5, 13))
    with pytest.raises(ValueError, match="cams.txt.*FOV.*image_undistorter"):
        colmap_to_pinhole("FOV", [1, 1, 1, 1, 0.1], source="cams.txt")
    with pytest.raises(ValueError, match="needs 4 parameters"):
        colmap_to_pinhole("PINHOLE", [1, 2, 3])
