"""Nerfstudio folders (`coin_cl.scene.nerfstudio`): a fixture written in nerfstudio's documented
layout (transforms.json, OpenGL camera-to-world, global and per-frame intrinsics, mask_path with
0 = left out) loads back to the cameras and object masks it was built from; ns-process-data's
colmap/sparse/0 points go through applied_transform; bad input is one line."""

import json

import numpy as np
import pytest

from coin_cl.scene import load_scene
from coin_cl.scene.colmap import ColmapCamera, write_model
from coin_cl.scene.conventions import look_at
from coin_cl.scene.io import write_png

W, H = 32, 24


def _views(n=4):
    """Known cameras (coin-cl convention: OpenCV world-to-camera) and object masks."""
    rng = np.random.default_rng(0)
    views = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 0.5 * i, 3 * np.sin(a)])
        V = look_at(eye, np.zeros(3), np.array([0.0, -1.0, 0.0]))
        K = np.array([[40.0 + i, 0, 16.0 + 0.5 * i], [0, 42.0 + i, 12.0], [0, 0, 1]])
        m = np.zeros((H, W), bool)
        m[4 + i : 12 + i, 6:20] = True
        img = rng.random((H, W, 3)).astype(np.float32)
        views.append((f"frame_{i:05d}.png", V, K, m, img))
    return views


def _write_ns(root, views, per_frame_k=False, masks=True, extra=None):
    frames = []
    for name, V, K, m, img in views:
        write_png(root / "images" / name, img)
        c2w_gl = np.linalg.inv(V) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV -> OpenGL camera axes
        fr = {"file_path": f"images/{name}", "transform_matrix": c2w_gl.tolist()}
        if per_frame_k:
            fr.update(fl_x=K[0, 0], fl_y=K[1, 1], cx=K[0, 2], cy=K[1, 2], w=W, h=H)
        if masks:
            write_png(root / "masks" / name, np.where(m, 0, 255).astype(np.uint8))  # 0 = ignore
            fr["mask_path"] = f"masks/{name}"
        frames.append(fr)
    doc = {"camera_model": "OPENCV", "frames": frames}
    if not per_frame_k:
        K = views[0][2]
        doc.update(fl_x=K[0, 0], fl_y=K[1, 1], cx=K[0, 2], cy=K[1, 2], w=W, h=H)
    doc.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


@pytest.mark.parametrize("per_frame_k", [False, True])
def test_poses_intrinsics_masks_equal_the_fixture(tmp_path, per_frame_k):
    views = _views()
    root = _write_ns(
        tmp_path / "ns", views, per_frame_k, extra={"test_filenames": ["images/frame_00003.png"]}
    )
    s = load_scene(root)
    assert s.meta["layout"] == "nerfstudio" and s.test_idx == [3] and s.train_idx == [0, 1, 2]
    for cam, img, m, (name, V, K, mask, im) in zip(s.cameras, s.images, s.masks, views, strict=True):
        assert cam.name == name and (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(cam.viewmat, V, atol=1e-9)
        np.testing.assert_allclose(cam.K, K if per_frame_k else views[0][2])
        np.testing.assert_array_equal(m, mask)  # nerfstudio 0 -> coin-cl object
        np.testing.assert_allclose(img, im, atol=1 / 255)
    # the camera looks at the origin: it projects in front of the camera near the principal point
    uv, z = s.cameras[1].project(np.zeros((1, 3)))
    assert z[0] > 0 and np.allclose(uv[0], s.cameras[1].K[:2, 2], atol=1e-6)


def test_ns_process_data_points_through_applied_transform(tmp_path):
    views = _views(3)
    A = np.eye(4)[:3][[0, 2, 1]]
    A[2] *= -1  # ns-process-data's COLMAP -> nerfstudio world
    root = _write_ns(tmp_path / "ns", views, masks=False, extra={"applied_transform": A.tolist()})
    pts = np.array([[0.1, 0.2, 0.3], [-1.0, 0.5, 2.0]])
    cam = ColmapCamera("PINHOLE", W, H, np.array([40.0, 42.0, 16.0, 12.0]))
    write_model(root / "colmap" / "sparse" / "0", cam, [], [], pts, np.full((2, 3), 200, np.uint8), text=True)
    s = load_scene(root)
    np.testing.assert_allclose(s.points, pts @ A[:, :3].T, atol=1e-6)
    assert s.masks[0].sum() == 0 and s.test_idx == []  # no masks, no split: a capture to train on


def test_masks_all_empty_is_an_error(tmp_path):
    views = [(n, V, K, np.zeros_like(m), im) for n, V, K, m, im in _views(2)]
    root = _write_ns(tmp_path / "ns", views)
    with pytest.raises(ValueError, match=r"ns: no view has a non-empty object mask.*transforms\.json"):
        load_scene(root)


def test_bad_transforms_are_one_line(tmp_path):
    root = _write_ns(tmp_path / "ns", _views(2), masks=False)
    doc = json.loads((root / "transforms.json").read_text())
    doc["frames"][1]["file_path"] = "../outside.png"
    (root / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"frame 1: file_path '\.\./outside\.png' points outside"):
        load_scene(root)
    del doc["fl_x"]
    doc["frames"][1]["file_path"] = "images/frame_00001.png"
    (root / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"frame 0: intrinsics \['fl_x'\] missing"):
        load_scene(root)
    (root / "transforms.json").write_text("{not json")
    with pytest.raises(ValueError, match="transforms.json is not valid JSON"):
        load_scene(root)
