"""Insertion from a text prompt (`coin-cl run --prompt`): without Stable Diffusion 2 weights it is a
clear error naming where to give them (no silent fallback to the prompt-less scene prior); with the
tiny random SD2 pipeline of the diffusion tests the prompt reaches the text encoder and changes
stage 1's inpaints."""

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
