"""Scene prior: learns a synthetic texture and fills a held-out hole with texture closer to the truth
than OpenCV TELEA (GMSD, high-frequency ratio); cache reuse; bad input."""

import logging

import numpy as np
import pytest
import torch
from coin_cl.diffusion.inpaint2d import InpaintConfig, inpaint_image, opencv_inpaint
from coin_cl.diffusion.sampling import SamplerConfig
from coin_cl.diffusion.scene_prior import (
    ScenePriorConfig,
    cache_key,
    heldout_x0_error,
    random_holes,
    train_scene_prior,
)

from coin_cl import metrics
from coin_cl.checkpoint import load_checkpoint


def texture(seed: int, n: int = 128) -> np.ndarray:
    """Coloured brick-like grating (periods 8 and 16 px) with a random phase and mild pixel noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    ph = rng.uniform(0, 2 * np.pi, 2)
    a = 0.5 + 0.25 * np.sin(2 * np.pi * x / 8 + ph[0]) * np.sign(np.sin(2 * np.pi * y / 16 + ph[1]))
    img = np.stack([a, 0.6 * a + 0.2, 1 - a], -1) + rng.normal(0, 0.03, (n, n, 3))
    return np.clip(img, 0, 1).astype(np.float32)


def gmsd(ref: np.ndarray, img: np.ndarray) -> float:
    return metrics.gmsd(img, ref)


def hf_energy_ratio(img: np.ndarray, truth: np.ndarray, m: np.ndarray) -> float:
    """Gradient energy in the hole, fill over truth (`metrics.hf_ratio` at power 2)."""
    return metrics.hf_ratio(img, truth, m, power=2)


# Steps, not seconds: a loaded machine (CI at idle priority) trains the same 120 steps.
CFG = ScenePriorConfig(patch=32, base=16, scales=(1,), batch=16, lr=2e-3, train_steps=120)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    torch.set_num_threads(2)
    imgs = [texture(s) for s in range(4)]
    cache = tmp_path_factory.mktemp("prior_cache")
    prior = train_scene_prior(imgs, None, CFG, cache_dir=cache, progress=False)
    return prior, imgs, cache


def test_learns_heldout_denoising(trained):
    prior, _, _ = trained
    assert prior.info["steps"] == 120 and not prior.info["cached"]
    test = texture(99)
    P = CFG.patch
    x0 = (
        torch.stack(
            [
                torch.from_numpy(test[y : y + P, x : x + P].transpose(2, 0, 1))
                for y, x in [(0, 0), (40, 60), (90, 10), (60, 90)]
            ]
        )
        * 2
        - 1
    )
    hole = torch.stack(
        [torch.from_numpy(random_holes(np.random.default_rng(i), P))[None].float() for i in range(4)]
    )
    e = heldout_x0_error(prior, x0, hole, [50, 200, 400, 600, 800], torch.Generator().manual_seed(0))
    assert e["model"] < 0.5 * e["identity"], e
    assert e["model"] < 0.5 * e["mean"], e  # beats the best constant fill too


def test_fill_beats_telea_in_texture(trained, caplog):
    prior, _, _ = trained
    test = texture(99)
    hole = np.zeros((128, 128), bool)
    hole[50:74, 56:80] = True
    with caplog.at_level(logging.DEBUG):  # the per-call source line is debug (a pipeline logs it once)
        out, src = inpaint_image(
            test,
            hole,
            scene_prior=prior,
            seed=0,
            cfg=InpaintConfig(sampler_prior=SamplerConfig(num_steps=25)),
        )
    assert src == "scene prior" and "scene prior" in caplog.text
    assert np.array_equal(out[~hole], test[~hole])
    tel = opencv_inpaint(test, hole, "telea")
    bb = (slice(50, 74), slice(56, 80))
    g_p, g_t = gmsd(test[bb], out[bb]), gmsd(test[bb], tel[bb])
    hf_p, hf_t = hf_energy_ratio(out, test, hole), hf_energy_ratio(tel, test, hole)
    mse_p, mse_t = float(((out - test)[hole] ** 2).mean()), float(((tel - test)[hole] ** 2).mean())
    print(
        f"masked PSNR prior {-10 * np.log10(mse_p):.2f} dB, telea {-10 * np.log10(mse_t):.2f} dB; "
        f"GMSD {g_p:.3f} vs {g_t:.3f}; HF ratio {hf_p:.2f} vs {hf_t:.2f}"
    )
    assert g_p < g_t
    assert abs(hf_p - 1) < abs(hf_t - 1)


def test_cache_reused_and_keyed(trained, caplog):
    prior, imgs, cache = trained
    with caplog.at_level(logging.INFO):
        again = train_scene_prior(imgs, None, CFG, cache_dir=cache, progress=False)
    assert again.info["cached"] and "reusing cached" in caplog.text and "scene prior" in caplog.text
    for a, b in zip(prior.net.state_dict().values(), again.net.state_dict().values()):
        assert torch.equal(a, b)
    assert not list(cache.glob("*.tmp"))
    ex = [np.zeros((128, 128), bool) for _ in imgs]
    k0 = cache_key(imgs, ex, CFG)
    ex[1][3, 4] = True
    assert cache_key(imgs, ex, CFG) != k0  # an exclusion change is a different prior


def test_holes_never_inside_exclusions():
    from coin_cl.diffusion.scene_prior import _PatchSampler

    img = texture(1, 64)
    exc = np.zeros((64, 64), bool)
    exc[:, :40] = True  # most of the image is "object": patches must overlap it
    s = _PatchSampler([img], [exc], ScenePriorConfig(patch=32, base=16, scales=(1,), batch=32))
    x0, hole, w = s.batch()
    assert x0.shape == (32, 3, 32, 32) and hole.shape == w.shape == (32, 1, 32, 32)
    # where the exclusion is, the hole is set (unknown) and the loss weight is 0
    assert bool(((w == 0) <= (hole == 1)).all())
    assert float(w.sum()) > 0


def test_bad_inputs():
    with pytest.raises(ValueError, match="no training images"):
        train_scene_prior([], cfg=CFG)
    bad = texture(0)
    bad[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="image 0 contains NaN"):
        train_scene_prior([bad], cfg=CFG)
    with pytest.raises(ValueError, match="exclusion mask 0"):
        train_scene_prior([texture(0)], [np.zeros((5, 5), bool)], cfg=CFG)


def test_steps_mode_resumes_after_a_kill_to_the_same_model(tmp_path, monkeypatch):
    """train_steps fixes the run: killed after step 3 (checkpoint after every step here) and called
    again, the training resumes at step 3 and ends with the weights an uninterrupted run makes."""
    import coin_cl.diffusion.scene_prior as sp

    cfg = ScenePriorConfig(patch=16, base=8, scales=(1,), batch=2, train_steps=6, train_seconds=0.0)
    imgs = [texture(s, 48) for s in range(2)]
    ref = train_scene_prior(imgs, None, cfg, cache_dir=tmp_path / "ref", progress=False)
    assert ref.info["steps"] == 6  # train_seconds=0 is ignored in steps mode

    real, calls = sp.denoising_loss, []

    def dying(*a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt  # the kill, inside step 4
        return real(*a, **k)

    monkeypatch.setattr(sp, "denoising_loss", dying)
    with pytest.raises(KeyboardInterrupt):
        train_scene_prior(imgs, None, cfg, cache_dir=tmp_path / "run", progress=False, ckpt_seconds=0.0)
    (ck,) = (tmp_path / "run").glob("*.ckpt.pt")
    assert load_checkpoint(ck)["steps"] == 3
    monkeypatch.setattr(sp, "denoising_loss", real)
    res = train_scene_prior(imgs, None, cfg, cache_dir=tmp_path / "run", progress=False)
    assert res.info["steps"] == 6 and not list((tmp_path / "run").glob("*.ckpt.pt"))
    for k, v in ref.net.state_dict().items():
        assert torch.equal(v, res.net.state_dict()[k]), k


def test_steps_for_seconds_matches_the_measured_rate():
    from coin_cl.diffusion.scene_prior import steps_for_seconds

    assert steps_for_seconds(120) == 133 and steps_for_seconds(0) == 1


def test_scene_prior_probe_measures_a_positive_rate():
    """The plan's probe of the prior's step time: finite and positive on a tiny network, with bad
    rates refused where they are turned into steps."""
    from coin_cl.diffusion.scene_prior import ScenePriorConfig, probe_seconds_per_step, steps_for_seconds

    spp = probe_seconds_per_step(ScenePriorConfig(base=8, batch=2, patch=16), steps=1)
    assert np.isfinite(spp) and 0 < spp < 10
    assert steps_for_seconds(120.0, 0.9) == 133 and steps_for_seconds(0.1, 5.0) == 1
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="seconds per step"):
            steps_for_seconds(120.0, bad)


@pytest.mark.parametrize("which", ["cache", "training checkpoint"])
def test_a_hostile_cached_prior_is_refused_without_running(tmp_path, which):
    """The cache (scene_prior_<key>.pt) and its training checkpoint (.ckpt.pt) come from the run
    folder, which may come from anyone: a planted file that would run code is refused, in one line
    naming it."""
    from coin_cl.checkpoint import CheckpointError
    from coin_cl.testing import hostile_checkpoint

    cfg = ScenePriorConfig(patch=16, base=8, scales=(1,), batch=2, train_steps=2, train_seconds=0.0)
    imgs = [texture(0, 48)]
    path = tmp_path / f"scene_prior_{cache_key(imgs, [np.zeros((48, 48), bool)], cfg)}.pt"
    if which != "cache":
        path = path.with_name(path.stem + ".ckpt.pt")
    hostile_checkpoint(path, tmp_path / "marker")
    with pytest.raises(CheckpointError, match="refused") as exc:
        train_scene_prior(imgs, None, cfg, cache_dir=tmp_path, progress=False)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    assert "the scene prior is trained again" in str(exc.value)
    assert not (tmp_path / "marker").exists()
