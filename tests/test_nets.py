"""coin_cl.nets: the LPIPS and Inception networks load through the real file layouts, bad files and
unset variables give errors / reasons that name the variable and the file, nothing is downloaded."""

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from coin_cl import metrics as M
from coin_cl.nets.inception import FID_ENV, inception_from_env, load_inception
from coin_cl.nets.lpips import LPIPS_ENV, load_lpips, lpips_from_env
from coin_cl.nets.weights import WeightFile, load_state_dict


def _pair(seed, H=40, W=48):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 1, (H, W, 3))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    return pred, gt


# ---------------------------------------------------------------- the weight rule


def test_weight_file_unset_set_and_missing(tmp_path, monkeypatch):
    wf = WeightFile("COIN_TEST_WEIGHTS", "the test file test.pth")
    monkeypatch.delenv(wf.env, raising=False)
    assert wf.path() is None
    monkeypatch.setenv(wf.env, "")
    assert wf.path() is None
    monkeypatch.setenv(wf.env, str(tmp_path / "absent.pth"))
    with pytest.raises(FileNotFoundError, match=r"COIN_TEST_WEIGHTS=.*absent\.pth.*the test file test\.pth"):
        wf.path()
    (tmp_path / "w.pth").write_bytes(b"")
    monkeypatch.setenv(wf.env, str(tmp_path / "w.pth"))
    assert wf.path() == tmp_path / "w.pth"


def test_a_variable_naming_a_missing_file_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv(FID_ENV, str(tmp_path / "nope.pth"))
    with pytest.raises(FileNotFoundError, match="COIN_FID_WEIGHTS=.*nope.pth.*pt_inception"):
        inception_from_env()
    monkeypatch.setenv(LPIPS_ENV[0], str(tmp_path / "nope.pth"))
    monkeypatch.setenv(LPIPS_ENV[1], str(tmp_path / "nope.pth"))
    with pytest.raises(FileNotFoundError, match="COIN_LPIPS_BACKBONE=.*nope.pth"):
        lpips_from_env()


def test_load_state_dict_names_the_file(tmp_path):
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pth"):
        load_state_dict(tmp_path / "junk.pth")
    torch.save({"state_dict": {"w": torch.ones(2)}}, tmp_path / "ckpt.pth")
    assert list(load_state_dict(tmp_path / "ckpt.pth")) == ["w"]
    torch.save([1, 2], tmp_path / "list.pth")
    with pytest.raises(ValueError, match="list.pth does not hold a state_dict"):
        load_state_dict(tmp_path / "list.pth")


def test_nets_never_download():
    banned = ("urllib", "requests", "http", "torch.hub", "huggingface_hub", "torchvision")
    root = Path(__file__).resolve().parents[1] / "coin_cl" / "nets"
    for f in root.glob("*.py"):
        tree = ast.parse(f.read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not [n for n in names for b in banned if n == b or n.startswith(b + ".")], f
        assert "hub" not in f.read_text().replace("huggingface", ""), f


# ---------------------------------------------------------------- LPIPS


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_loads_through_real_loader(lpips_files, tmp_path, net):
    b, h, backbone, heads = lpips_files(tmp_path, net)
    model = load_lpips(b, h, net)
    torch.testing.assert_close(model.features[0].weight, backbone["features.0.weight"])
    torch.testing.assert_close(model.lins[4].weight, heads["lin4.model.1.weight"])
    pred, gt = _pair(3, 40, 40)
    d = M.lpips(model, pred, gt)
    assert d > 0
    assert M.lpips(model, gt, gt) == pytest.approx(0.0, abs=1e-7)
    assert M.lpips(model, gt, pred) == pytest.approx(d, rel=1e-5)
    further = np.clip(gt + np.random.default_rng(4).normal(0, 0.3, gt.shape), 0, 1)
    assert M.lpips(model, further, gt) > d


def test_lpips_bad_files_name_the_file(lpips_files, tmp_path):
    b, h, _, _ = lpips_files(tmp_path, "alex")
    with pytest.raises(ValueError, match="alex_backbone.pth.*vgg"):
        load_lpips(b, h, "vgg")
    with pytest.raises(ValueError, match="alex_backbone.pth.*heads"):
        load_lpips(b, b, "alex")
    with pytest.raises(FileNotFoundError, match="absent.pth"):
        load_lpips(tmp_path / "absent.pth", h)


def test_lpips_unavailable_without_weights(monkeypatch):
    for k in LPIPS_ENV:
        monkeypatch.delenv(k, raising=False)
    model, reason = lpips_from_env()
    assert model is None and "COIN_LPIPS_BACKBONE" in reason
    pred, gt = _pair(5)
    out = M.evaluate_view(pred, gt, np.ones(gt.shape[:2], bool))
    assert out["lpips"] is None and out["m_lpips"] is None


def test_lpips_from_env(lpips_files, tmp_path, monkeypatch):
    b, h, _, _ = lpips_files(tmp_path, "alex", seed=1)
    monkeypatch.setenv("COIN_LPIPS_BACKBONE", str(b))
    monkeypatch.setenv("COIN_LPIPS_HEADS", str(h))
    model, reason = lpips_from_env()
    assert reason is None
    pred, gt = _pair(6, 48, 48)
    mask = np.zeros((48, 48), bool)
    mask[10:20, 10:20] = True
    out = M.evaluate_view(pred, gt, mask, model)
    assert out["lpips"] > 0 and out["m_lpips"] > 0


# ---------------------------------------------------------------- FID


def test_inception_loads_through_real_loader(inception_file, tmp_path):
    path, sd = inception_file
    model = load_inception(path)
    torch.testing.assert_close(model.Mixed_7c.branch_pool.conv.weight, sd["Mixed_7c.branch_pool.conv.weight"])
    rng = np.random.default_rng(10)
    imgs = [rng.uniform(0, 1, (40, 56, 3)) for _ in range(3)]
    f = M.inception_features(model, imgs)
    assert f.shape == (3, 2048) and np.isfinite(f).all() and f.std() > 0
    bad = {k: v for k, v in sd.items() if not k.startswith("Mixed_7c")}
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="bad.pth.*Mixed_7c"):
        load_inception(tmp_path / "bad.pth")


def test_fid_unavailable_without_weights(monkeypatch):
    monkeypatch.delenv(FID_ENV, raising=False)
    model, reason = inception_from_env()
    assert model is None and "COIN_FID_WEIGHTS" in reason
