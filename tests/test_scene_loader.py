"""load_scene on the real SPIn-NeRF scene, plain COLMAP folders, our own format, and bad input."""

import json
import logging
import shutil

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from coin_cl.scene import load_scene, save_scene
from coin_cl.scene.colmap import ColmapCamera, Undistorter, write_model
from coin_cl.scene.conventions import k_for_opencv
from coin_cl.scene.geometry import mask_vote_counts, object_points
from coin_cl.scene.io import write_png
from coin_cl.scene.synthetic import make_synthetic, write_synthetic


@pytest.fixture(scope="module")
def syn():
    return make_synthetic(coverage=90, seed=5, n_views=8, width=64, height=48, n_points=800)


@pytest.fixture(scope="module")
def syn_dir(syn, tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("loader") / "scene", syn)


@pytest.fixture
def scene_copy(syn_dir, tmp_path):
    d = tmp_path / "copy"
    shutil.copytree(syn_dir, d)
    return d


def _plain_colmap(syn, root, model="PINHOLE", params=None, masks=True):
    """A plain COLMAP folder (images/, sparse/0 text model, masks/) from a synthetic scene."""
    for j, c in enumerate(syn.cameras):
        write_png(root / "images" / c.name, syn.present[j])
        if masks:
            write_png(root / "masks" / c.name, syn.masks[j].astype(np.uint8) * 255)
    K = syn.cameras[0].K
    p = params if params is not None else [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    cam = ColmapCamera(model, syn.cameras[0].width, syn.cameras[0].height, np.array(p, float))
    write_model(
        root / "sparse" / "0",
        cam,
        [c.name for c in syn.cameras],
        [c.viewmat for c in syn.cameras],
        syn.points,
        (syn.colors * 255).astype(np.uint8),
        text=True,
    )
    return root


# ---------------------------------------------------------------- the real SPIn-NeRF scene


@pytest.fixture(scope="module")
def real(spinnerf_dir):
    return load_scene(spinnerf_dir)


@pytest.mark.real_data
def test_real_scene_layout(real):
    assert len(real) == 39
    assert real.test_idx == [0, 1, 2, 3, 4] and len(real.train_idx) == 34
    assert real.names[0] == "20220819_104221.png"
    cam = real.cameras[0]
    assert (cam.width, cam.height) == (1008, 567)
    np.testing.assert_allclose(cam.K[[0, 1, 0, 1], [0, 1, 2, 2]], [767.2934841, 767.2934841, 504, 283.5])
    assert all(m.shape == (567, 1008) for m in real.masks)  # the 576-row test labels are cropped
    assert all(real.masks[i].any() for i in range(39))
    assert real.points.shape == (73437, 3) and real.colors is None  # zero colours = unknown
    assert set(real.priors) == {"rgb", "depth"} and len(real.priors["rgb"]) == 34
    assert real.priors["depth"][real.train_idx[0]].shape == (567, 1008)
    assert real.meta["view_index"][:5] == [0, 10, 20, 29, 39]


@pytest.mark.real_data
def test_real_points_project_within_bounds(real):
    for i in range(0, len(real), 4):
        cam = real.cameras[i]
        uv, z = cam.project(real.points)
        inside = cam.in_image(uv) & (z > 0)
        assert inside.mean() > 0.6
        zin = z[inside]
        within = (zin >= 0.9 * real.near[i]) & (zin <= 1.1 * real.far[i])
        assert within.mean() > 0.98


@pytest.mark.real_data
def test_real_train_masks_agree_with_test_masks(real):
    idx = object_points(real)
    assert len(idx) > 1000
    views = real.test_idx
    seen, inside = mask_vote_counts(
        real.points[idx], [real.cameras[i] for i in views], [real.masks[i] for i in views]
    )
    assert seen.sum() > 1000
    assert inside.sum() / seen.sum() >= 0.95


@pytest.mark.real_data
def test_real_scene_half_resolution(spinnerf_dir, real):
    half = load_scene(spinnerf_dir, resolution=0.5, priors=False)
    cam = half.cameras[3]
    assert half.images[3].shape == (284, 504, 3) and half.masks[3].shape == (284, 504)
    assert half.masks[3].dtype == bool
    np.testing.assert_allclose(cam.K[0, 0], 767.2934841 / 2)
    np.testing.assert_allclose(cam.K[1, 2], 283.5 * 284 / 567)
    # the mask shrinks by area, not by shape
    assert half.masks[3].sum() == pytest.approx(real.masks[3].sum() / 4, rel=0.05)


@pytest.mark.real_data
def test_real_scene_undistort_option(spinnerf_dir):
    u = load_scene(spinnerf_dir, undistort=True, priors=False)
    assert u.meta["undistorted"]
    assert u.images[0].shape == (567, 1008, 3)


# ---------------------------------------------------------------- plain COLMAP and our format


def test_plain_colmap_folder(syn, tmp_path):
    root = _plain_colmap(syn, tmp_path / "plain")
    sc = load_scene(root)
    assert sc.meta["layout"] == "colmap" and sc.test_idx == [] and len(sc.train_idx) == 8
    for a, b in zip(sc.cameras, syn.cameras, strict=True):
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-6)
    np.testing.assert_array_equal(sc.masks[2], syn.masks[2])
    sc2 = load_scene(root, n_test=2)
    assert sc2.test_idx == [0, 1]
    np.testing.assert_array_equal(sc2.masks[1], syn.masks[1])  # held-out views keep masks/


def test_plain_colmap_distortion_is_undone(syn, tmp_path):
    K = syn.cameras[0].K
    k1 = 0.08
    root = _plain_colmap(syn, tmp_path / "dist", "SIMPLE_RADIAL", [K[0, 0], K[0, 2], K[1, 2], k1])
    sc = load_scene(root)
    assert sc.meta["undistorted"]
    und = Undistorter(K, np.array([k1, 0, 0, 0]), False, 64, 48)
    np.testing.assert_allclose(sc.images[1], und.image(syn.present[1]), atol=1 / 255)
    np.testing.assert_array_equal(sc.masks[1], und.mask(syn.masks[1]))
    raw = load_scene(root, undistort=False)
    assert not np.allclose(raw.images[1], sc.images[1], atol=2 / 255)


def test_undistorter_moves_a_point_to_its_pinhole_position():
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    dist = np.array([0.2, -0.05, 0.0, 0.0])
    und = Undistorter(K, dist, False, 128, 96)
    x = np.array([[[0.45, 0.3, 1.0]]])  # camera ray
    pu = (x[0, 0, :2] / x[0, 0, 2]) * 100 + [64, 48]  # pinhole position, our convention
    pd, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k_for_opencv(K), dist)
    pd = pd.reshape(2) + 0.5  # back to our pixel convention
    img = np.zeros((96, 128, 3), np.float32)
    cv2.circle(
        img,
        (int(round(pd[0] * 16 - 8)), int(round(pd[1] * 16 - 8))),
        24,
        (1, 1, 1),
        -1,
        lineType=cv2.LINE_AA,
        shift=4,
    )
    out = und.image(img)[..., 0]
    ys, xs = np.mgrid[0:96, 0:128]
    c = np.array([(out * (xs + 0.5)).sum(), (out * (ys + 0.5)).sum()]) / out.sum()
    assert np.linalg.norm(pd - pu) > 2  # distortion is visible here
    assert np.linalg.norm(c - pu) < 0.5


def test_project_format_round_trip(syn_dir, tmp_path):
    a = load_scene(syn_dir)
    a.ref_view = 4
    save_scene(a, tmp_path / "own")
    b = load_scene(tmp_path / "own")
    assert b.names == a.names and b.test_idx == a.test_idx and b.ref_view == 4
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        np.testing.assert_array_equal(ca.viewmat, cb.viewmat)
        np.testing.assert_array_equal(ca.K, cb.K)
    for i in range(len(a)):
        np.testing.assert_allclose(b.images[i], a.images[i], atol=0.5 / 255 + 1e-6)
        np.testing.assert_array_equal(b.masks[i], a.masks[i])
    np.testing.assert_array_equal(b.points, a.points)
    np.testing.assert_array_equal(b.extras["depth"][5], a.extras["depth"][5])
    np.testing.assert_allclose(b.near, a.near)


def test_resolution_option_scales_k_and_keeps_geometry(syn_dir):
    full = load_scene(syn_dir)
    half = load_scene(syn_dir, resolution=0.5)
    assert half.images[0].shape == (24, 32, 3) and half.masks[0].dtype == bool
    uv_f, _ = full.cameras[2].project(full.points[:50])
    uv_h, _ = half.cameras[2].project(full.points[:50])
    np.testing.assert_allclose(uv_h, uv_f * 0.5, atol=1e-9)


# ---------------------------------------------------------------- bad input


def test_missing_train_mask_names_file(scene_copy):
    (scene_copy / "images_4" / "label" / "view_005.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"label/view_005\.png"):
        load_scene(scene_copy)


def test_missing_test_mask_names_file(scene_copy):
    (scene_copy / "images_4" / "test_label" / "out_00002.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"out_00002\.png"):
        load_scene(scene_copy)


def test_mask_size_mismatch_names_file(scene_copy):
    iio.imwrite(scene_copy / "images_4" / "label" / "view_004.png", np.zeros((30, 40), np.uint8))
    with pytest.raises(ValueError, match=r"view_004\.png.*40x30.*64x48"):
        load_scene(scene_copy)


def test_whole_image_mask_names_file(scene_copy):
    iio.imwrite(scene_copy / "images_4" / "label" / "view_006.png", np.ones((48, 64), np.uint8))
    with pytest.raises(ValueError, match=r"view_006\.png.*whole image"):
        load_scene(scene_copy)


def test_empty_mask_warns_and_keeps_view(scene_copy, caplog):
    iio.imwrite(scene_copy / "images_4" / "label" / "view_007.png", np.zeros((48, 64), np.uint8))
    with caplog.at_level(logging.WARNING):
        sc = load_scene(scene_copy)
    assert len(sc) == 8 and not sc.masks[7].any()
    assert "view_007.png" in caplog.text and "empty" in caplog.text


def test_view_without_pose_names_file(scene_copy):
    shutil.copy(scene_copy / "images_4" / "view_003.png", scene_copy / "images_4" / "view_999.png")
    shutil.copy(
        scene_copy / "images_4" / "label" / "view_003.png", scene_copy / "images_4" / "label" / "view_999.png"
    )
    (scene_copy / "views.txt").unlink()
    with pytest.raises(ValueError, match=r"view_999\.png has no pose"):
        load_scene(scene_copy)


def test_view_without_pose_in_llff_names_file(scene_copy):
    (scene_copy / "sparse" / "0" / "images.bin").unlink()
    pb = np.load(scene_copy / "poses_bounds.npy")
    np.save(scene_copy / "poses_bounds.npy", pb[:6])
    with pytest.raises(ValueError, match=r"poses_bounds\.npy.*6 rows"):
        load_scene(scene_copy)


def test_unknown_camera_model_names_file(scene_copy):
    model = scene_copy / "sparse" / "0"
    (model / "images.bin").unlink()
    (model / "cameras.bin").unlink()
    (model / "cameras.txt").write_text("1 WEIRD_LENS 64 48 50 32 24\n")
    with pytest.raises(ValueError, match=r"cameras\.txt.*WEIRD_LENS"):
        load_scene(scene_copy)


def test_unsupported_camera_model_names_model(syn, tmp_path):
    root = _plain_colmap(syn, tmp_path / "fov", "FOV", [50, 50, 32, 24, 0.9])
    with pytest.raises(ValueError, match=r"sparse/0.*FOV.*image_undistorter"):
        load_scene(root)


def test_no_poses_and_no_images(tmp_path):
    (tmp_path / "images").mkdir()
    write_png(tmp_path / "images" / "a.png", np.zeros((8, 8, 3)))
    with pytest.raises(FileNotFoundError, match="no camera poses.*run COLMAP"):
        load_scene(tmp_path)
    with pytest.raises(FileNotFoundError, match="not_here"):
        load_scene(tmp_path / "not_here")


def test_truncated_image_names_file_and_what_to_do(scene_copy):
    p = scene_copy / "images_4" / "view_004.png"
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"image .*view_004\.png cannot be read .*truncated or not an image"):
        load_scene(scene_copy)


def test_unreadable_image_names_file(scene_copy):
    (scene_copy / "images_4" / "view_005.png").write_bytes(b"this is not a picture at all" * 10)
    with pytest.raises(ValueError, match=r"view_005\.png cannot be read"):
        load_scene(scene_copy)


@pytest.mark.parametrize("kind", ["grey", "rgba", "16bit"])
def test_grey_rgba_and_16bit_images_are_read_as_rgb(scene_copy, kind):
    p = scene_copy / "images_4" / "view_006.png"
    rgb = iio.imread(p)[..., :3]
    if kind == "grey":
        iio.imwrite(p, rgb[..., 1])
        want = np.repeat(rgb[..., 1:2], 3, 2) / 255.0
    elif kind == "rgba":
        iio.imwrite(p, np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 7, np.uint8)], 2))
        want = rgb / 255.0  # alpha dropped, colour as stored
    else:  # 16-bit colour (PIL reads it at 8 bits: the same picture to 1/255)
        cv2.imwrite(str(p), rgb[..., ::-1].astype(np.uint16) * 257)
        want = rgb / 255.0
    sc = load_scene(scene_copy)
    assert sc.images[6].shape == (48, 64, 3) and sc.images[6].dtype == np.float32
    np.testing.assert_allclose(sc.images[6], want, atol=1e-6)


def test_duplicate_names_are_refused(scene_copy):
    img = scene_copy / "images_4" / "view_002.png"
    iio.imwrite(img.with_suffix(".jpg"), iio.imread(img))
    with pytest.raises(
        ValueError, match=r"same name.*view_002\.jpg.*view_002\.png|view_002\.png.*view_002\.jpg"
    ):
        load_scene(scene_copy)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_or_inf_in_llff_poses_and_bounds_names_the_row(scene_copy, bad):
    (scene_copy / "sparse" / "0" / "images.bin").unlink()
    pb0 = np.load(scene_copy / "poses_bounds.npy")
    pb = pb0.copy()
    pb[3, 5] = bad  # a pose entry
    np.save(scene_copy / "poses_bounds.npy", pb)
    with pytest.raises(
        ValueError, match=r"pose of image view_003\.png in .*poses_bounds\.npy holds NaN or Inf"
    ):
        load_scene(scene_copy)
    pb = pb0.copy()
    pb[2, -1] = bad  # far bound
    np.save(scene_copy / "poses_bounds.npy", pb)
    with pytest.raises(ValueError, match=r"near/far bounds of image view_002\.png"):
        load_scene(scene_copy)


def test_nan_in_colmap_pose_names_the_image(syn, tmp_path):
    root = _plain_colmap(syn, tmp_path / "nan")
    V = [c.viewmat.copy() for c in syn.cameras]
    V[4][0, 3] = np.nan
    K = syn.cameras[0].K
    cam = ColmapCamera("PINHOLE", 64, 48, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    for f in (root / "sparse" / "0").iterdir():
        f.unlink()
    names = [c.name for c in syn.cameras]
    write_model(root / "sparse" / "0", cam, names, V, syn.points, (syn.colors * 255).astype(np.uint8))
    with pytest.raises(ValueError, match=rf"pose of image {names[4]} in COLMAP model .*holds NaN or Inf"):
        load_scene(root)


def test_colmap_model_naming_missing_images_loads_the_rest(syn, tmp_path, caplog):
    root = _plain_colmap(syn, tmp_path / "missing")
    for sub in ("images", "masks"):
        (root / sub / syn.cameras[2].name).unlink()
    with caplog.at_level(logging.INFO):
        sc = load_scene(root)
    assert len(sc) == len(syn.cameras) - 1 and syn.cameras[2].name not in [c.name for c in sc.cameras]
    assert "have no file" in caplog.text and syn.cameras[2].name in caplog.text


def test_paths_with_spaces_and_non_ascii_letters(syn_dir, tmp_path):
    d = tmp_path / "my scène – ünïcode 場景"
    shutil.copytree(syn_dir, d)
    sc = load_scene(d)
    assert len(sc) == 8 and sc.path == d


# ---------------------------------------------------------------- GScream / FreeInpaint's SPIn-NeRF copies


def _lama_layout(syn, root):
    """The layout GScream's and FreeInpaint's loaders read: images_4/<stem>.png, sparse/0,
    lama_input/<stem>_mask.png (training masks), images_4/mask_test/<stem>.png (test masks)."""
    _plain_colmap(syn, root, masks=False)
    (root / "images").rename(root / "images_4")
    for j, c in enumerate(syn.cameras):
        stem = c.name.rsplit(".", 1)[0]
        m = syn.masks[j].astype(np.uint8) * 255
        if syn.is_test[j]:
            write_png(root / "images_4" / "mask_test" / f"{stem}.png", m)
        else:
            write_png(root / "lama_input" / f"{stem}_mask.png", m)
    return root


def test_gscream_freeinpaint_masks_load(syn, tmp_path):
    root = _lama_layout(syn, tmp_path / "gs")
    n_test = sum(syn.is_test)
    assert syn.is_test[:n_test] == [True] * n_test  # the synthetic scene puts its test views first
    s = load_scene(root, n_test=n_test)
    assert s.meta["layout"] == "spinnerf"
    for j in range(len(syn.cameras)):
        np.testing.assert_array_equal(s.masks[j], syn.masks[j])
    assert any(m.any() for m in s.masks)


def test_masks_present_but_all_empty_is_an_error(syn, tmp_path):
    root = _lama_layout(syn, tmp_path / "gs")
    for p in (root / "lama_input").glob("*.png"):
        write_png(p, np.zeros((syn.cameras[0].height, syn.cameras[0].width), np.uint8))
    for p in (root / "images_4" / "mask_test").glob("*.png"):
        write_png(p, np.zeros((syn.cameras[0].height, syn.cameras[0].width), np.uint8))
    with pytest.raises(ValueError, match=r"gs: no view has a non-empty object mask \(looked in .*lama_input"):
        load_scene(root, n_test=2)


# ---------------------------------------------------------------- 360-USID


def _usid(syn, root):
    """360-USID as FreeInpaint's loader reads it: images/ + object_masks/ (training, with the
    object), test_images/ (object absent), <scene>_masks/<k:05d>.png, reference/, sparse/0."""
    _plain_colmap(syn, root, masks=False)
    test_names = sorted(c.name for j, c in enumerate(syn.cameras) if syn.is_test[j])
    for j, c in enumerate(syn.cameras):
        m = syn.masks[j].astype(np.uint8) * 255
        if syn.is_test[j]:
            (root / "images" / c.name).unlink()
            write_png(root / "test_images" / c.name, syn.absent[j])
            write_png(root / "cone_masks" / f"{test_names.index(c.name):05d}.png", m)
        else:
            write_png(root / "object_masks" / c.name, m)
    ref = next(c.name for j, c in enumerate(syn.cameras) if not syn.is_test[j])
    write_png(root / "reference" / ref, syn.present[syn.is_test.index(False)])
    return root, ref


def test_usid_layout(syn, tmp_path):
    root, ref = _usid(syn, tmp_path / "cone")
    s = load_scene(root)
    assert s.meta["layout"] == "360-usid"
    by_name = {c.name: j for j, c in enumerate(syn.cameras)}
    assert sorted(s.cameras[i].name for i in s.test_idx) == sorted(
        c.name for j, c in enumerate(syn.cameras) if syn.is_test[j]
    )
    for i, cam in enumerate(s.cameras):
        j = by_name[cam.name]
        np.testing.assert_allclose(cam.viewmat, syn.cameras[j].viewmat, atol=1e-6)
        np.testing.assert_array_equal(s.masks[i], syn.masks[j])
        want = syn.absent[j] if syn.is_test[j] else syn.present[j]
        np.testing.assert_allclose(s.images[i], want, atol=1 / 255)
    assert s.cameras[s.ref_view].name == ref


# ---------------------------------------------------------------- hostile files: one line naming them


def _one_line(exc, *parts):
    msg = str(exc.value)
    assert "\n" not in msg, msg
    for p in parts:
        assert str(p) in msg, (p, msg)
    return msg


def test_scene_json_path_leading_outside_the_folder_is_refused(syn, tmp_path):
    """Every path scene.json names must resolve inside the scene folder: "../x.png", an absolute
    path or a symlink out is refused before anything is read."""
    root = save_scene(load_scene(write_synthetic(tmp_path / "w", syn)), tmp_path / "native")
    secret = tmp_path / "secret.png"
    write_png(secret, np.zeros((4, 4, 3), np.float32))
    doc = json.loads((root / "scene.json").read_text())
    for field, bad in (("image", "../secret.png"), ("image", str(secret)), ("mask", "../secret.png")):
        d = json.loads(json.dumps(doc))
        d["views"][1][field] = bad
        (root / "scene.json").write_text(json.dumps(d))
        with pytest.raises(ValueError) as e:
            load_scene(root)
        _one_line(e, root / "scene.json", f"views[1].{field}", "outside the scene folder")
    d = json.loads(json.dumps(doc))
    d["points"] = "../../points.ply"
    (root / "scene.json").write_text(json.dumps(d))
    with pytest.raises(ValueError) as e:
        load_scene(root)
    _one_line(e, root / "scene.json", "points")


def test_scene_json_malformed_or_unknown_keys_name_the_field(syn, tmp_path):
    root = save_scene(load_scene(write_synthetic(tmp_path / "w", syn)), tmp_path / "native")
    doc = json.loads((root / "scene.json").read_text())
    for change, field in (({"views": {}}, "views is"), ({"train_idx": [0, 99]}, "train_idx holds view 99"),
                          ({"bogus": 1}, "unknown key bogus")):  # fmt: skip
        (root / "scene.json").write_text(json.dumps({**doc, **change}))
        with pytest.raises(ValueError) as e:
            load_scene(root)
        _one_line(e, root / "scene.json", field)
    d = json.loads(json.dumps(doc))
    d["views"][0]["K"][0][0] = 0.0
    (root / "scene.json").write_text(json.dumps(d))
    with pytest.raises(ValueError) as e:
        load_scene(root)
    _one_line(e, root / "scene.json", "views[0]", "focal length 0")


@pytest.mark.parametrize(
    ("line", "what"),
    [("-1  view_001.png  train", "view index -1"), ("1  view_001.png", "line 3 is not"),
     ("x  view_001.png  train", "line 3 is not"), ("1  view_001.png  maybe", "split 'maybe'"),
     ("99  view_001.png  train", "view index 99 has no pose")],
)  # fmt: skip
def test_views_txt_bad_line_or_index_names_file_and_line(scene_copy, line, what):
    """A views.txt index out of range (negative included: it must not take the last pose row) or a
    malformed line: one line naming views.txt."""
    (scene_copy / "sparse" / "0" / "images.bin").unlink()  # poses from poses_bounds.npy by index
    lines = (scene_copy / "views.txt").read_text().splitlines()
    lines[2] = line  # the line of view_001 (after the header and view_000)
    (scene_copy / "views.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError) as e:
        load_scene(scene_copy)
    _one_line(e, "views.txt", what)


@pytest.mark.parametrize("bad", ["garbage", "pickle", "shape"])
def test_poses_bounds_that_is_not_an_array_names_the_file(scene_copy, bad):
    (scene_copy / "sparse" / "0" / "images.bin").unlink()
    pb = scene_copy / "poses_bounds.npy"
    if bad == "garbage":
        pb.write_bytes(b"\x93NUMPY garbage" * 3)
    elif bad == "pickle":
        np.save(pb, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    else:
        np.save(pb, np.zeros((6, 5)))
    with pytest.raises(ValueError) as e:
        load_scene(scene_copy)
    _one_line(e, pb, "re-create it")


@pytest.mark.parametrize(("value", "shown"), [(0.0, "focal length 0"), (np.nan, "parameters [nan"),
                                              (-5.0, "focal length -5")])  # fmt: skip
def test_llff_focal_not_positive_names_file_and_value(scene_copy, value, shown):
    (scene_copy / "sparse" / "0" / "images.bin").unlink()
    (scene_copy / "sparse" / "0" / "cameras.bin").unlink()  # the focal comes from poses_bounds.npy
    pb = np.load(scene_copy / "poses_bounds.npy")
    pb[:, 14] = value
    np.save(scene_copy / "poses_bounds.npy", pb)
    with pytest.raises(ValueError) as e:
        load_scene(scene_copy)
    _one_line(e, "poses_bounds.npy", shown)


def test_all_zero_rotation_names_file_and_image(scene_copy):
    (scene_copy / "sparse" / "0" / "images.bin").unlink()
    pb = np.load(scene_copy / "poses_bounds.npy")
    pb[2, [0, 1, 2, 5, 6, 7, 10, 11, 12]] = 0.0
    np.save(scene_copy / "poses_bounds.npy", pb)
    with pytest.raises(ValueError) as e:
        load_scene(scene_copy)
    _one_line(e, "poses_bounds.npy", "view_002.png", "is not a rotation matrix")


def test_colmap_text_focal_zero_and_bad_lines_name_file_and_line(syn, tmp_path):
    root = _plain_colmap(syn, tmp_path / "c")
    cams = root / "sparse" / "0" / "cameras.txt"
    text = cams.read_text()
    line = next(ln for ln in text.splitlines() if ln and not ln.startswith("#"))
    t = line.split()
    cams.write_text(text.replace(line, " ".join([*t[:4], "0", *t[5:]])))
    with pytest.raises(ValueError) as e:
        load_scene(root)
    _one_line(e, "sparse/0", "focal length 0")
    cams.write_text(text.replace(line, " ".join(t[:3])))
    from coin_cl.scene.colmap import read_cameras, read_points3d

    with pytest.raises(ValueError) as e:
        read_cameras(root / "sparse" / "0")
    _one_line(e, cams, "is not 'CAMERA_ID MODEL")
    pts = root / "sparse" / "0" / "points3D.txt"
    pts.write_text("# header\n1 0.5 0.5 nope 1 2 3 0.1\n")
    with pytest.raises(ValueError) as e:
        read_points3d(root / "sparse" / "0")
    _one_line(e, pts, "line 2 is not")


def test_colmap_binary_truncated_names_the_file(scene_copy):
    from coin_cl.scene.colmap import read_cameras, read_points3d

    for name, read in (("cameras.bin", read_cameras), ("points3D.bin", read_points3d)):
        p = scene_copy / "sparse" / "0" / name
        p.write_bytes(p.read_bytes()[:30])
        with pytest.raises(ValueError) as e:
            read(scene_copy / "sparse" / "0")
        _one_line(e, p, "truncated or not a COLMAP")
