"""Metrics: agreement with scikit-image, masked variants by hand, LPIPS loading, `coin-cl eval`."""

import json
import math

import cv2
import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from coin_cl import metrics as M


def _pair(seed, H=40, W=48):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 1, (H, W, 3))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    return pred, gt


def test_psnr_ssim_equal_scikit_image():
    pred, gt = _pair(0)
    assert M.psnr(pred, gt) == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0))
    ref = structural_similarity(
        gt,
        pred,
        data_range=1.0,
        channel_axis=-1,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )
    assert M.ssim(pred, gt) == pytest.approx(ref)
    # scikit-image's mean leaves out the 5 px border the 11 px window cannot cover
    assert M.ssim_map(pred, gt)[5:-5, 5:-5].mean() == pytest.approx(ref, rel=1e-9)
    assert M.psnr(gt, gt) == math.inf and M.ssim(gt, gt) == pytest.approx(1.0)


def test_masked_psnr_by_hand():
    gt = np.zeros((2, 3, 3))
    pred = np.zeros((2, 3, 3))
    pred[0, 0] = 0.1  # inside the mask
    pred[1, 2] = 0.5  # outside: must not count
    mask = np.array([[True, True, False], [False, False, False]])
    # mse over 2 pixels x 3 channels = (3 * 0.01) / 6
    assert M.masked_psnr(pred, gt, mask) == pytest.approx(10 * np.log10(1 / 0.005))
    assert M.masked_psnr(pred, gt, ~mask) < M.masked_psnr(pred, gt, mask)
    assert math.isnan(M.masked_psnr(pred, gt, np.zeros((2, 3), bool)))
    assert M.masked_psnr(gt, gt, mask) == math.inf


def test_masked_ssim_is_map_mean_inside_mask():
    pred, gt = _pair(1)
    mask = np.zeros(gt.shape[:2], bool)
    mask[10:20, 5:30] = True
    pred2 = pred.copy()
    pred2[~mask] = gt[~mask]  # perfect outside the mask
    S = M.ssim_map(pred2, gt)
    assert M.masked_ssim(pred2, gt, mask) == pytest.approx(S[mask].mean())
    # far from the mask the map is exactly 1 and inside it is not
    assert np.allclose(S[35:, 40:], 1.0) and M.masked_ssim(pred2, gt, mask) < 0.99


def test_bbox_crop_by_hand():
    m = np.zeros((40, 50), bool)
    m[10:25, 20:40] = True
    m[12, 15] = True
    rows, cols = M.bbox_crop(m)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (10, 25, 15, 40)
    tiny = np.zeros((40, 50), bool)
    tiny[0, 49] = True  # a corner pixel grows to the 11 px SSIM window, clipped to the image
    rows, cols = M.bbox_crop(tiny)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (0, 11, 39, 50)
    assert M.bbox_crop(np.zeros((5, 5), bool)) is None
    pred, gt = _pair(2)
    mb = np.zeros(gt.shape[:2], bool)
    mb[5:30, 8:40] = True
    got = M.bbox_metrics(pred, gt, mb)
    assert got["bbox_psnr"] == pytest.approx(M.psnr(pred[5:30, 8:40], gt[5:30, 8:40]))
    assert got["bbox_ssim"] == pytest.approx(M.ssim(pred[5:30, 8:40], gt[5:30, 8:40]))


def test_aggregate_handles_inf_nan_none():
    views = [
        {"psnr": 20.0, "m_psnr": math.nan, "lpips": None},
        {"psnr": 30.0, "m_psnr": 10.0, "lpips": None},
    ]
    agg = M.aggregate(views)
    assert agg == {"psnr": 25.0, "m_psnr": 10.0, "lpips": None}
    assert M.aggregate([{"psnr": math.inf}, {"psnr": 20.0}])["psnr"] == math.inf
    assert M.jsonable({"a": [math.inf, math.nan, 1.0]}) == {"a": ["inf", "nan", 1.0]}


# ---------------------------------------------------------------- LPIPS


def _random_lpips_files(tmp_path, net, seed=0):
    """Random weights under the real file layouts (torchvision backbone, lpips heads)."""
    torch.manual_seed(seed)
    feats, _, chans = M._features(net)
    backbone = {f"features.{k}": v for k, v in feats.state_dict().items()}
    backbone["classifier.1.weight"] = torch.zeros(3, 3)  # real files carry the classifier too
    heads = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(chans)}
    b, h = tmp_path / f"{net}_backbone.pth", tmp_path / f"{net}_heads.pth"
    torch.save(backbone, b)
    torch.save(heads, h)
    return b, h, backbone, heads


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_loads_through_real_loader(tmp_path, net):
    b, h, backbone, heads = _random_lpips_files(tmp_path, net)
    model = M.load_lpips(b, h, net)
    torch.testing.assert_close(model.features[0].weight, backbone["features.0.weight"])
    torch.testing.assert_close(model.lins[4].weight, heads["lin4.model.1.weight"])
    pred, gt = _pair(3, 40, 40)
    d = M.lpips(model, pred, gt)
    assert d > 0
    assert M.lpips(model, gt, gt) == pytest.approx(0.0, abs=1e-7)
    assert M.lpips(model, gt, pred) == pytest.approx(d, rel=1e-5)
    further = np.clip(gt + np.random.default_rng(4).normal(0, 0.3, gt.shape), 0, 1)
    assert M.lpips(model, further, gt) > d


def test_lpips_bad_files_name_the_file(tmp_path):
    b, h, _, _ = _random_lpips_files(tmp_path, "alex")
    with pytest.raises(ValueError, match="alex_backbone.pth.*vgg"):
        M.load_lpips(b, h, "vgg")
    with pytest.raises(ValueError, match="alex_backbone.pth.*heads"):
        M.load_lpips(b, b, "alex")
    with pytest.raises(FileNotFoundError, match="absent.pth"):
        M.load_lpips(tmp_path / "absent.pth", h)


def test_lpips_unavailable_without_weights(monkeypatch):
    for k in M.LPIPS_ENV:
        monkeypatch.delenv(k, raising=False)
    model, reason = M.lpips_from_env()
    assert model is None and "COIN_LPIPS_BACKBONE" in reason
    pred, gt = _pair(5)
    out = M.evaluate_view(pred, gt, np.ones(gt.shape[:2], bool))
    assert out["lpips"] is None and out["m_lpips"] is None


def test_lpips_from_env(tmp_path, monkeypatch):
    b, h, _, _ = _random_lpips_files(tmp_path, "alex", seed=1)
    monkeypatch.setenv("COIN_LPIPS_BACKBONE", str(b))
    monkeypatch.setenv("COIN_LPIPS_HEADS", str(h))
    model, reason = M.lpips_from_env()
    assert reason is None
    pred, gt = _pair(6, 48, 48)
    mask = np.zeros((48, 48), bool)
    mask[10:20, 10:20] = True
    out = M.evaluate_view(pred, gt, mask, model)
    assert out["lpips"] > 0 and out["m_lpips"] > 0


# ---------------------------------------------------------------- FID


def test_frechet_distance_by_hand():
    rng = np.random.default_rng(9)
    a = rng.normal(1.0, 2.0, (200, 1))
    b = rng.normal(-0.5, 0.5, (300, 1))
    # 1-D: (m1 - m2)^2 + (s1 - s2)^2 with the sample statistics
    want = (a.mean() - b.mean()) ** 2 + (a.std(ddof=1) - b.std(ddof=1)) ** 2
    assert M.frechet_distance(a, b) == pytest.approx(want, rel=1e-6)
    x = rng.normal(size=(50, 4)) @ rng.normal(size=(4, 4))
    y = rng.normal(size=(60, 4)) @ rng.normal(size=(4, 4)) + 0.3
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    w, V = np.linalg.eigh(s1)
    r1 = V @ np.diag(np.sqrt(w)) @ V.T  # tr sqrt(S1 S2) = tr sqrt(S1^1/2 S2 S1^1/2)
    tr = np.sqrt(np.clip(np.linalg.eigvalsh(r1 @ s2 @ r1), 0, None)).sum()
    d = x.mean(0) - y.mean(0)
    want = d @ d + np.trace(s1) + np.trace(s2) - 2 * tr
    assert M.frechet_distance(x, y) == pytest.approx(want, rel=1e-6)
    assert M.frechet_distance(x, x) == pytest.approx(0.0, abs=1e-6)
    # more samples than dimensions goes through scipy's sqrtm: same value
    big_x, big_y = np.repeat(x, 2, axis=0)[:9], y[:9]
    narrow = M.frechet_distance(big_x[:, :3], big_y[:, :3])
    s1, s2 = np.cov(big_x[:, :3], rowvar=False), np.cov(big_y[:, :3], rowvar=False)
    w, V = np.linalg.eigh(s1)
    r1 = V @ np.diag(np.sqrt(np.clip(w, 0, None))) @ V.T
    tr = np.sqrt(np.clip(np.linalg.eigvalsh(r1 @ s2 @ r1), 0, None)).sum()
    d = big_x[:, :3].mean(0) - big_y[:, :3].mean(0)
    assert narrow == pytest.approx(d @ d + np.trace(s1) + np.trace(s2) - 2 * tr, rel=1e-6)


@pytest.fixture(scope="module")
def inception_file(tmp_path_factory):
    """pytorch-fid's state_dict layout with random weights (BN statistics made non-trivial)."""
    torch.manual_seed(0)
    model = M._inception_module()()
    sd = model.state_dict()
    for k, v in sd.items():
        if k.endswith("running_var"):
            sd[k] = torch.rand_like(v) + 0.5
        elif k.endswith("running_mean"):
            sd[k] = torch.randn_like(v) * 0.1
    sd = {k: v for k, v in sd.items() if not k.endswith("num_batches_tracked")}  # as the real file
    p = tmp_path_factory.mktemp("fid") / "pt_inception.pth"
    torch.save(sd, p)
    return p, sd


def test_inception_loads_through_real_loader(inception_file, tmp_path):
    path, sd = inception_file
    model = M.load_inception(path)
    torch.testing.assert_close(model.Mixed_7c.branch_pool.conv.weight, sd["Mixed_7c.branch_pool.conv.weight"])
    rng = np.random.default_rng(10)
    imgs = [rng.uniform(0, 1, (40, 56, 3)) for _ in range(3)]
    f = M.inception_features(model, imgs)
    assert f.shape == (3, 2048) and np.isfinite(f).all() and f.std() > 0
    bad = {k: v for k, v in sd.items() if not k.startswith("Mixed_7c")}
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="bad.pth.*Mixed_7c"):
        M.load_inception(tmp_path / "bad.pth")


def test_fid_unavailable_without_weights(monkeypatch):
    monkeypatch.delenv(M.FID_ENV, raising=False)
    model, reason = M.inception_from_env()
    assert model is None and "COIN_FID_WEIGHTS" in reason


# ---------------------------------------------------------------- coin-cl eval


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
    from coin_cl.scene.io import read_image

    for k in (*M.LPIPS_ENV, M.FID_ENV):
        monkeypatch.delenv(k, raising=False)
    pred = tmp_path / "pred"
    pred.mkdir()
    for n in ("view_000.png", "view_001.png"):
        (pred / n).write_bytes((eval_scene / "images_4" / n).read_bytes())
    assert main(["eval", str(pred), "--scene", str(eval_scene)]) == 0
    doc = json.loads((pred / "eval" / "metrics.json").read_text())
    assert doc["mean"]["psnr"] == "inf" and doc["mean"]["m_psnr"] == "inf"
    assert doc["mean"]["ssim"] == pytest.approx(1.0) and doc["mean"]["m_ssim"] == pytest.approx(1.0)
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
    from coin_cl.scene.io import read_image, write_png

    pred = tmp_path / "pred"
    for n in ("view_000.png", "view_001.png"):
        img = read_image(eval_scene / "images_4" / n)
        present = read_image(eval_scene / "images_4" / "present" / n)  # object not removed
        write_png(pred / n, present)
        assert not np.array_equal(img, present)
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out")
    assert 10 < doc["mean"]["psnr"] < 60 and doc["mean"]["m_psnr"] < doc["mean"]["psnr"]
    assert doc["mean"]["m_ssim"] < doc["mean"]["ssim"] < 1


def test_eval_missing_prediction_names_view(eval_scene, tmp_path):
    from coin_cl.evaluation import evaluate_folder

    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / "view_000.png").write_bytes((eval_scene / "images_4" / "view_000.png").read_bytes())
    with pytest.raises(FileNotFoundError, match="view_001.png"):
        evaluate_folder(pred, eval_scene)


def test_eval_with_weight_files_reports_lpips_and_fid(eval_scene, tmp_path, monkeypatch, inception_file):
    # Wiring only: the weights are random, so the values mean nothing beyond "computed, finite".
    from coin_cl.evaluation import evaluate_folder

    b, h, _, _ = _random_lpips_files(tmp_path, "alex", seed=2)
    monkeypatch.setenv("COIN_LPIPS_BACKBONE", str(b))
    monkeypatch.setenv("COIN_LPIPS_HEADS", str(h))
    monkeypatch.setenv(M.FID_ENV, str(inception_file[0]))
    pred = tmp_path / "pred"
    pred.mkdir()
    for n in ("view_000.png", "view_001.png"):
        (pred / n).write_bytes((eval_scene / "images_4" / "present" / n).read_bytes())
    doc = evaluate_folder(pred, eval_scene, tmp_path / "out")
    mean = doc["mean"]
    assert doc["lpips"] == "available" and doc["fid"] == "available"
    assert mean["lpips"] > 0 and mean["m_lpips"] > 0
    assert math.isfinite(mean["fid"]) and math.isfinite(mean["m_fid"])


def test_hf_ratio_and_gmsd_see_blur():
    rng = np.random.default_rng(3)
    gt = rng.random((64, 64, 3)).astype(np.float32)
    blur = cv2.GaussianBlur(gt, (0, 0), 2.0)
    mask = np.zeros((64, 64), bool)
    mask[16:48, 16:48] = True
    assert M.hf_ratio(gt, gt, mask) == pytest.approx(1.0)
    assert M.hf_ratio(blur, gt, mask) < 0.5  # a smear
    assert M.hf_ratio(gt, blur, mask) > 2.0  # stronger texture than the truth
    assert M.hf_ratio(blur, gt, mask, power=2) < M.hf_ratio(blur, gt, mask)
    assert math.isnan(M.hf_ratio(gt, gt, np.zeros((64, 64), bool)))
    flat = np.full((64, 64, 3), 0.5, np.float32)
    assert math.isnan(M.hf_ratio(gt, flat, mask))
    assert M.gmsd(gt, gt) == pytest.approx(0.0, abs=1e-9)
    assert M.bbox_gmsd(blur, gt, mask) > 0.05
    assert math.isnan(M.bbox_gmsd(gt, gt, np.zeros((64, 64), bool)))
    v = M.evaluate_view(blur, gt, mask)
    assert v["hf_ratio"] < 0.5 and v["bbox_gmsd"] > 0.05
