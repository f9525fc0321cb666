"""Insertion from a text prompt (`coin-cl run --prompt`): without Stable Diffusion 2 weights it is a
clear error naming where to give them (no silent fallback to the prompt-less scene prior); with the
tiny random SD2 pipeline of the diffusion tests the prompt reaches the text encoder and changes
stage 1's inpaints; a text insertion draws the reference once and lifts it into every view."""

import numpy as np
import pytest
from coin_cl.diffusion.inpaint2d import InpaintConfig
from coin_cl.diffusion.sampling import SamplerConfig
from coin_cl.diffusion.sd2 import SD2Denoiser
from test_diffusion_sd2 import _tiny_pipeline

from coin_cl.cli import main
from coin_cl.pipeline.coin import inpaint
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig, run_inpaint2d
from coin_cl.scene import load_scene, write_synthetic
from coin_cl.scene.io import read_image


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("room"), n_views=8, width=64, height=48, seed=0)


def test_prompt_without_weights_is_a_clear_error(room, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("COIN_SD2_PATH", raising=False)
    with pytest.raises(ValueError, match="COIN_SD2_PATH") as e:
        inpaint(room, tmp_path / "a", prompt="a red apple")
    assert "--sd-path" in str(e.value)
    assert not (tmp_path / "a").exists()  # nothing started
    rc = main(["run", str(room), "--out", str(tmp_path / "b"), "--prompt", "a red apple"])
    assert rc == 2 and "COIN_SD2_PATH" in capsys.readouterr().err


def test_prompt_reaches_the_text_encoder(room, tmp_path):
    (tmp_path / "sd2").mkdir()
    den = SD2Denoiser.from_pretrained(_tiny_pipeline(tmp_path / "sd2"))
    e0, e1, e2 = (den.encode_prompt(p) for p in ("", "a red apple", "a blue car"))
    assert not np.allclose(e1.numpy(), e2.numpy()) and not np.allclose(e0.numpy(), e1.numpy())
    scene = load_scene(room)
    views = list(scene.train_idx)[:2]
    cfg = Inpaint2DConfig(inpaint=InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=3)))
    outs = {}
    for p in ("a red apple", "a blue car"):
        res = run_inpaint2d(scene, scene.masks, views, tmp_path / p, cfg, sd2=den, prompt=p)
        assert res["sources"] == ["Stable Diffusion 2 inpainting"]
        outs[p] = [read_image(tmp_path / p / "images" / (scene.cameras[i].name.rsplit(".", 1)[0] + ".png"))
                   for i in views]  # fmt: skip
    for i, a, b in zip(views, outs["a red apple"], outs["a blue car"], strict=True):
        m = scene.masks[i]
        assert np.array_equal(a[~m], b[~m])  # outside the mask: the capture, whatever the prompt
        assert np.abs(a[m] - b[m]).mean() > 1e-3  # inside: the conditioning changed the fill


def test_a_prompt_is_drawn_once_and_lifted_into_every_view(room, tmp_path):
    """With SD2 (the tiny random pipeline), a text insertion draws the prompt into the reference's
    mask alone, then lifts it like an edited photo: every other view's stage-1 image is the capture
    with the lifted object warped in, CLG is left out, and the run goes to the end."""
    from dataclasses import replace

    from coin_cl.diffusion.scene_prior import ScenePriorConfig

    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.scene.masks import read_mask

    (tmp_path / "sd2").mkdir()
    sd = _tiny_pipeline(tmp_path / "sd2")
    icfg = Inpaint2DConfig(inpaint=InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=2)),
                           prior=ScenePriorConfig(patch=32, base=8, max_steps=2))  # fmt: skip
    cfg = CoInConfig(sd_path=str(sd), iters_refgs=3, iters_ted_finetune=2, iters_ted_adversarial=0,
                     inpaint2d=icfg, refgs=RefGSConfig(depth_prior_iters=5), mask_dilate=0)  # fmt: skip
    out = tmp_path / "run"
    res = inpaint(room, out, config=replace(cfg, prompt="a red box"))
    st = res.stages
    assert st["1_inpaint"]["result"]["sources"] == ["Stable Diffusion 2 inpainting (the reference), lifted"]
    assert st["1_inpaint"]["result"]["lifted_points"] > 0
    assert st["3_clg"]["status"].startswith("skipped: an insertion")
    assert st["4_ted"]["status"] == "ran" and res.ply.is_file()
    drawn = sorted((out / "1_inpaint" / "prompt" / "images").glob("*.png"))
    assert len(drawn) == 1  # SD2 ran on the reference alone
    scene = load_scene(room)
    stems = [c.name.rsplit(".", 1)[0] for c in scene.cameras]
    k = stems.index(drawn[0].stem)
    ref_image = read_image(out / "1_inpaint" / "images" / drawn[0].name)
    np.testing.assert_array_equal(ref_image, read_image(drawn[0]))  # the reference: SD2's answer as drawn
    moved = 0
    for i in scene.train_idx:
        if i == k:
            continue
        img = read_image(out / "1_inpaint" / "images" / f"{stems[i]}.png")
        foot = read_mask(out / "1_inpaint" / "footprints" / f"{stems[i]}.png", scene.masks[i].shape)
        cap = scene.images[i]
        assert np.abs(img[~foot] - cap[~foot]).max() < 1.5 / 255  # outside the footprint: the capture
        moved += foot.any() and np.abs(img[foot] - cap[foot]).mean() > 0.02  # inside: the object warped in
    assert moved >= 2


def test_a_prompt_sd2_leaves_empty_is_a_clear_error(room, tmp_path, monkeypatch):
    """SD2's fill equal to the capture (nothing drawn) stops the run in stage 1 with what to do."""
    import coin_cl.pipeline.stages as stages
    from coin_cl.pipeline.coin import CoInConfig

    (tmp_path / "sd2").mkdir()
    sd = _tiny_pipeline(tmp_path / "sd2")
    scene = load_scene(room)
    captures = lambda sc, folder, views: {i: scene.images[i] for i in views}  # noqa: E731
    monkeypatch.setattr(stages, "read_inpaints", captures)
    icfg = Inpaint2DConfig(inpaint=InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=1)))
    cfg = CoInConfig(sd_path=str(sd), iters_refgs=2, inpaint2d=icfg, prompt="a red box")
    with pytest.raises(ValueError, match="drew nothing for the prompt 'a red box'.*reword the prompt"):
        inpaint(room, tmp_path / "run", config=cfg)
    assert not (tmp_path / "run" / "2_refgs").exists()
