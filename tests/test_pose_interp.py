"""interpolate_pose: centres lerped, rotations slerped (paper 4.3's intermediate viewpoint)."""

import numpy as np
import pytest
import torch

from coin_cl.scene.conventions import (
    interpolate_pose,
    make_viewmat,
    quat_wxyz_to_rotmat,
    rotmat_to_quat_wxyz,
    slerp_quat,
)


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = np.radians(deg) / 2
    return quat_wxyz_to_rotmat(np.concatenate([[np.cos(h)], np.sin(h) * axis]))


def _pose(R, centre):
    return make_viewmat(R, -R @ np.asarray(centre, float))


def _centre(V):
    return -V[:3, :3].T @ V[:3, 3]


def test_alpha_0_and_1_are_exact():
    rng = np.random.default_rng(0)
    a = _pose(_rot(rng.normal(size=3), 40), rng.normal(size=3))
    b = _pose(_rot(rng.normal(size=3), 75), rng.normal(size=3))
    assert np.array_equal(interpolate_pose(a, b, 0.0), a)
    assert np.array_equal(interpolate_pose(a, b, 1.0), b)
    ta = torch.from_numpy(a)
    out = interpolate_pose(ta, torch.from_numpy(b), 0.0)
    assert isinstance(out, torch.Tensor) and torch.equal(out, ta)


def test_midpoint_about_one_axis_is_half_angle_and_centres_lerp():
    axis = [0.3, -1.0, 0.2]
    a = _pose(_rot(axis, 10), [1.0, 2.0, 3.0])
    b = _pose(_rot(axis, 70), [3.0, -2.0, 5.0])
    for alpha in (0.5, 0.25):
        m = interpolate_pose(a, b, alpha)
        np.testing.assert_allclose(m[:3, :3], _rot(axis, 10 + 60 * alpha), atol=1e-12)
        np.testing.assert_allclose(_centre(m), (1 - alpha) * _centre(a) + alpha * _centre(b), atol=1e-12)
        np.testing.assert_allclose(m[3], [0, 0, 0, 1])


def test_pure_rotation_keeps_the_centre():
    """Lerping the translation column would move a camera that only rotates; centres do not."""
    c = [0.5, -1.0, 2.0]
    m = interpolate_pose(_pose(_rot([0, 1, 0], -40), c), _pose(_rot([0, 1, 0], 60), c))
    np.testing.assert_allclose(_centre(m), c, atol=1e-12)
    np.testing.assert_allclose(m[:3, :3], _rot([0, 1, 0], 10), atol=1e-12)


def test_nearly_equal_rotations():
    R = _rot([1, 2, 3], 33)
    a = _pose(R, [0, 0, 0])
    b = _pose(_rot([1, 2, 3], 33 + 1e-9), [0, 0, 1])
    m = interpolate_pose(a, b, 0.5)
    assert np.all(np.isfinite(m))
    np.testing.assert_allclose(m[:3, :3], R, atol=1e-10)
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-14)
    m_same = interpolate_pose(a, a, 0.5)
    np.testing.assert_allclose(m_same, a, atol=1e-15)


def test_opposite_quaternions_are_the_same_rotation():
    q = rotmat_to_quat_wxyz(_rot([0.2, 0.5, -1], 120))
    out = slerp_quat(q, -q, 0.5)
    np.testing.assert_allclose(np.abs(out @ q), 1.0, atol=1e-15)
    # 180-degree apart rotations (orthogonal quaternions) still interpolate on a great circle
    a, b = _rot([0, 0, 1], 0), _rot([0, 0, 1], 180)
    m = interpolate_pose(_pose(a, [0, 0, 0]), _pose(b, [0, 0, 0]), 0.5)
    np.testing.assert_allclose(m[:3, :3], _rot([0, 0, 1], 90), atol=1e-12)
    # w = 0 quaternion built both ways round: q and -q give the identical pose
    R = _rot([1, 0, 0], 180)
    m = interpolate_pose(_pose(R, [1, 0, 0]), _pose(R, [1, 0, 0]), 0.3)
    np.testing.assert_allclose(m[:3, :3], R, atol=1e-12)


def test_bad_input_is_a_clear_error():
    a = _pose(_rot([0, 1, 0], 10), [0, 0, 0])
    bad = a.copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        interpolate_pose(a, bad)
    with pytest.raises(ValueError, match="NaN"):
        interpolate_pose(torch.from_numpy(bad), torch.from_numpy(a))
    with pytest.raises(ValueError, match="shape"):
        interpolate_pose(a[:3], a)
    with pytest.raises(ValueError, match="rotation"):
        interpolate_pose(a, np.diag([2.0, 1, 1, 1]))
