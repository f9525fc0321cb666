"""coin_cl.prepare.holdout: photos held out of the mapping, localized in the model of the others and
written as test views with their region masks (the synthetic capture, known cameras and masks)."""

import numpy as np
import pytest

from coin_cl.prepare import Annotation, SfmConfig, prepare
from coin_cl.prepare.align import pose_errors
from coin_cl.prepare.holdout import read_test_list, resolve_holdout
from coin_cl.prepare.propagate import iou
from coin_cl.scene.io import write_png

HELD = ["view_003.png", "view_008.png"]
# The localized poses are held to the mapped views' tolerances of test_prepare_sfm.py. Measured
# (one run): held out 0.26 / 0.27 deg and 0.0024 / 0.0032 units, the mapped views' worst 0.36 deg /
# 0.0044 units; 281 and 310 inliers.
MAX_ROT_DEG = 1.0
MAX_CENTRE = 0.02
# Region masks drawn on the photos, carried through the resize (none here) and undistortion
# (SIMPLE_RADIAL fitted on a distortion-free render: a pixel at most; measured IoU 1.0).
MIN_MASK_IOU = 0.95


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """12 photos of the room from known cameras, an image of noise, the object's true masks (as
    the held-out photos' region masks), and the annotation mask of view 0."""
    import cv2

    from coin_cl.prepare.capture import synthetic_capture

    d = tmp_path_factory.mktemp("photos")
    cap = synthetic_capture(d, n_views=12, width=256, height=192)
    noise = np.random.default_rng(0).uniform(0, 1, (48, 64, 3)).astype(np.float32)
    write_png(d / "zz_noise.png", cv2.resize(noise, (256, 192), interpolation=cv2.INTER_NEAREST))
    masks = tmp_path_factory.mktemp("held_masks")
    for c, m in zip(cap.cameras, cap.masks, strict=True):
        write_png(masks / c.name, m.astype(np.uint8) * 255)
    return d, masks, {c.name: c for c in cap.cameras}, {c.name: m for c, m in zip(cap.cameras, cap.masks)}


@pytest.fixture(scope="module")
def prepared(capture, tmp_path_factory):
    photos, masks, _, _ = capture
    out = tmp_path_factory.mktemp("scene")
    ann = Annotation(view="view_000", mask=masks / "view_000.png")
    report, result = prepare(photos, out, ann, sfm=SfmConfig(width=256, num_threads=2),
                             holdout=[*HELD, "zz_noise"], holdout_masks=masks)  # fmt: skip
    return out, report, result


def test_held_out_photos_are_posed_test_views(capture, prepared):
    import coin_cl

    _, _, truth, _ = capture
    out, report, _ = prepared
    scene = coin_cl.load_scene(out)
    assert sorted(scene.names[i] for i in scene.test_idx) == HELD
    assert len(scene.train_idx) == 10 and not set(HELD) & set(report.registered)
    assert sorted(report.held_out) == HELD and min(v["inliers"] for v in report.held_out.values()) >= 30
    err = pose_errors([c.viewmat for c in scene.cameras], [truth[c.name].viewmat for c in scene.cameras])
    held = [scene.names.index(n) for n in HELD]
    assert err.rot_deg[held].max() < MAX_ROT_DEG, err.rot_deg[held]
    assert err.centre[held].max() < MAX_CENTRE, err.centre[held]


def test_held_out_photos_add_nothing_to_the_model(prepared):
    """No point is triangulated from a held-out photo: none of its features is in a track."""
    import pycolmap

    out, report, _ = prepared
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    for im in rec.images.values():
        assert (im.num_points3D == 0) == (im.name in HELD), im.name
    assert rec.num_points3D() == report.n_points


def test_held_out_masks_are_given_not_propagated(capture, prepared):
    import coin_cl

    _, _, _, truth = capture
    out, _, result = prepared
    scene = coin_cl.load_scene(out)
    for i in scene.test_idx:
        assert iou(scene.masks[i], truth[scene.names[i]]) > MIN_MASK_IOU
    assert len(result.masks) == 10  # propagated to the training views only
    assert all(scene.masks[i].any() for i in scene.train_idx)
    # the masks step run again (as a user re-annotating) keeps the held-out masks
    from coin_cl.prepare import make_masks

    make_masks(out, Annotation(view="view_000", mask=out / "masks" / "view_000.png"))
    again = coin_cl.load_scene(out)
    assert all(np.array_equal(again.masks[i], scene.masks[i]) for i in scene.test_idx)


def test_unplaceable_holdout_is_reported(prepared):
    out, report, _ = prepared
    assert "zz_noise.png" not in read_test_list(out)
    assert "held out, but only 0" in report.dropped["zz_noise.png"]
    assert "held out (test views" in (out / "prepare_report.txt").read_text()


def test_bad_holdout_arguments(capture, tmp_path):
    photos, masks, _, _ = capture
    names = [f"view_{i:03d}.png" for i in range(5)]
    assert resolve_holdout(names, ["view_001", "view_001.jpg"]) == ["view_001.png"]
    with pytest.raises(ValueError, match="--holdout nope: no photo"):
        resolve_holdout(names, ["nope"])
    with pytest.raises(ValueError, match="leaves 2 to train on"):
        resolve_holdout(names, names[:3])
    with pytest.raises(ValueError, match="needs --holdout"):
        prepare(photos, tmp_path / "a", holdout_masks=masks)
    with pytest.raises(ValueError, match="needs an annotation"):
        prepare(photos, tmp_path / "b", holdout=HELD, holdout_masks=masks)


def test_missing_or_misshapen_holdout_mask(prepared, tmp_path):
    from coin_cl.prepare.holdout import write_holdout_masks
    from coin_cl.scene.colmap import read_cameras

    out, _, _ = prepared
    cam = next(iter(read_cameras(out / ".prepare" / "sparse" / "best").values()))
    with pytest.raises(FileNotFoundError, match="no mask .*view_003.png"):
        write_holdout_masks(tmp_path, ["view_003.png"], tmp_path, cam)
    write_png(tmp_path / "view_003.png", np.zeros((100, 100), np.uint8))
    with pytest.raises(ValueError, match="not the photos' aspect ratio"):
        write_holdout_masks(tmp_path, ["view_003.png"], tmp_path, cam)


def test_cli_bad_holdout(tmp_path, capsys):
    """`coin-cl prepare --holdout`: an unknown photo or masks without held-out photos end in one line,
    exit 2, before anything is written."""
    from coin_cl.cli import main

    for i in range(4):
        write_png(tmp_path / f"p{i}.png", np.zeros((48, 64, 3), np.float32))
    out = tmp_path / "s"
    assert main(["prepare", str(tmp_path), "--out", str(out), "--holdout", "p9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--holdout p9: no photo" in err[0] and not out.exists()
    assert main(["prepare", str(tmp_path), "--out", str(out), "--holdout-masks", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs --holdout" in err[0] and not out.exists()
