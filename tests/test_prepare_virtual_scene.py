"""A removal scene from a capture, on the synthetic room written as a plain COLMAP capture (the room
without its object): the truth is known, so the benchmark's honesty can be checked."""

import json

import numpy as np
import pytest

from coin_cl.prepare.triangulate import TriangulateConfig
from coin_cl.prepare.virtual_scene import BoxSpec, VirtualSceneConfig, make_virtual_scene, natural_order
from coin_cl.scene import load_scene
from coin_cl.scene.colmap import ColmapCamera, write_model
from coin_cl.scene.io import imread_checked, to_uint8, write_png
from coin_cl.scene.synthetic import make_synthetic
from coin_cl.scene.virtual_object import render_box

BOX = BoxSpec((0.35, 0.2, 0.55), (0.3, 0.24, 0.22), yaw=31.0)  # on the table top (z = 0.5)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    room = make_synthetic(n_views=12, width=160, height=120, seed=0, n_points=6000, supersample=1)
    cap = tmp_path_factory.mktemp("capture")
    names = [f"{k + 1}.png" for k in range(len(room.cameras))]  # not zero-padded, as the cup's
    for n, img in zip(names, room.absent):
        write_png(cap / "images" / n, img)
    rng = np.random.default_rng(0)
    pts = []
    for cam, depth in zip(room.cameras, room.depth_absent):
        yy, xx = rng.integers(0, 120, 600), rng.integers(0, 160, 600)
        pts.append(cam.unproject(np.stack([xx + 0.5, yy + 0.5], 1), depth[yy, xx].astype(np.float64)))
    pts = np.concatenate(pts)
    K = room.cameras[0].K
    model = ColmapCamera("PINHOLE", 160, 120, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    write_model(cap / "sparse" / "0", model, names, [c.viewmat for c in room.cameras], pts,
                np.full((len(pts), 3), 128, np.uint8))  # fmt: skip
    out = tmp_path_factory.mktemp("made") / "scene"
    cfg = VirtualSceneConfig(
        test_every=4, triangulate=TriangulateConfig(width=160, neighbours=5, max_features=2048)
    )
    doc = make_virtual_scene(cap, out, BOX, cfg)
    return cap, out, doc, load_scene(cap, n_test=0), load_scene(out)


def test_load_scene_finds_test_views_and_masks(made):
    cap, out, doc, capture, scene = made
    assert scene.meta["layout"] == "coin-cl" and scene.test_idx and len(scene.train_idx) >= 3
    assert doc["n_views"]["test"] == len(scene.test_idx) and doc["n_views"]["train"] == len(scene.train_idx)
    assert all(scene.masks[i].any() for i in scene.test_idx)
    assert (out / "contact_sheet.png").is_file() and (out / "virtual_object.json").is_file()
    # test views: every 4th in natural order (1, 5, 9), unless the box is hidden there
    order = [capture.names[i] for i in natural_order(capture.names)]
    assert {scene.names[i] for i in scene.test_idx} <= set(order[::4])


def test_test_images_are_the_capture_files_byte_for_byte(made):
    cap, out, doc, capture, scene = made
    for i in scene.test_idx:
        name = scene.names[i]
        v = next(v for v in json.loads((out / "scene.json").read_text())["views"] if v["name"] == name)
        assert (out / v["image"]).read_bytes() == (cap / "images" / name).read_bytes()


def test_training_masks_are_the_exact_footprint_and_all_box(made):
    from coin_cl.prepare.virtual_scene import place_box

    cap, out, doc, capture, scene = made
    box, _ = place_box(capture, BOX, VirtualSceneConfig())
    doc_views = json.loads((out / "scene.json").read_text())["views"]
    for i in scene.train_idx:
        name = scene.names[i]
        r = render_box(box, scene.cameras[i], 3)
        assert np.array_equal(scene.masks[i], r["mask"])
        written = imread_checked(out / next(v["image"] for v in doc_views if v["name"] == name))[..., :3]
        orig = to_uint8(capture.images[capture.index(name)])
        m = r["mask"]
        assert m.any()
        # inside: the box's colour in every pixel (not one true pixel); outside: the capture's
        assert np.array_equal(written[m], to_uint8(r["rgb"])[m])
        assert np.array_equal(written[~m], orig[~m])
        assert (written[m] != orig[m]).any(axis=1).mean() > 0.95


def test_points_come_from_training_views_only_and_none_inside_the_box(made):
    from coin_cl.prepare.virtual_scene import place_box

    cap, out, doc, capture, scene = made
    box, _ = place_box(capture, BOX, VirtualSceneConfig())
    assert len(scene.points) > 10
    train = {scene.names[i] for i in scene.train_idx}
    assert set(doc["points"]["from_views"]) <= train
    assert not box.contains(scene.points, grow=VirtualSceneConfig().drop_margin * box.size.min()).any()
    assert doc["points"]["inside_box_dropped"] > 0  # the painted box's texture was triangulated, then dropped
    # triangulated with the true poses: the points lie on the room's surfaces or on the painted box
    assert doc["points"]["triangulated"] >= doc["points"]["kept"]


def test_a_box_cutting_through_geometry_or_an_occupied_out_is_refused(made, tmp_path):
    cap, out, doc, capture, scene = made
    with pytest.raises(FileExistsError, match="not empty"):
        make_virtual_scene(cap, out, BOX)
    from dataclasses import replace

    from coin_cl.prepare.virtual_scene import place_box

    box, _ = place_box(capture, BOX, VirtualSceneConfig())
    # real geometry where the box would stand (a cluster of sparse points inside it): refused
    blob = box.center + np.random.default_rng(0).normal(0, 0.02, (20, 3))
    with pytest.raises(ValueError, match="cuts through the scene"):
        place_box(replace(capture, points=np.concatenate([capture.points, blob])), BOX, VirtualSceneConfig())
    with pytest.raises(ValueError, match="positive"):  # nothing written on a bad call
        make_virtual_scene(cap, tmp_path / "x", BoxSpec((0, 0, 0), (0, 1, 1)))
    assert not (tmp_path / "x").exists() and not (tmp_path / ".x.tmp").exists()
