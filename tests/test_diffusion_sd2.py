"""SD2-inpainting path on a tiny random diffusers pipeline saved to a temporary folder (no weights)."""

import json

import numpy as np
import pytest
import torch
from coin_cl.diffusion.inpaint2d import InpaintConfig, inpaint_image
from coin_cl.diffusion.sampling import DDIMSampler, SamplerConfig
from coin_cl.diffusion.sd2 import SD2Denoiser, check_sd2_folder, missing_sd2_files


def _tiny_pipeline(root):
    from diffusers import AutoencoderKL, DDIMScheduler, StableDiffusionInpaintPipeline, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        block_out_channels=(32, 64),
        layers_per_block=1,
        sample_size=32,
        in_channels=9,
        out_channels=4,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        cross_attention_dim=32,
        attention_head_dim=8,
        norm_num_groups=8,
    )
    vae = AutoencoderKL(
        block_out_channels=[32, 64],
        in_channels=3,
        out_channels=3,
        down_block_types=["DownEncoderBlock2D"] * 2,
        up_block_types=["UpDecoderBlock2D"] * 2,
        latent_channels=4,
        norm_num_groups=8,
        sample_size=64,
    )
    te = CLIPTextModel(
        CLIPTextConfig(
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
            hidden_size=32,
            intermediate_size=37,
            num_attention_heads=4,
            num_hidden_layers=2,
            vocab_size=60,
            max_position_embeddings=77,
        )
    )
    tokdir = root / "_tok"
    tokdir.mkdir()
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in "abcdefghijklmnopqrstuvwxyz":
        vocab[c] = len(vocab)
        vocab[c + "</w>"] = len(vocab)
    (tokdir / "vocab.json").write_text(json.dumps(vocab))
    (tokdir / "merges.txt").write_text("#version: 0.2\n")
    tok = CLIPTokenizer(
        str(tokdir / "vocab.json"), str(tokdir / "merges.txt"), model_max_length=77, pad_token="<|endoftext|>"
    )
    sched = DDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        prediction_type="v_prediction",
        steps_offset=1,
    )
    pipe = StableDiffusionInpaintPipeline(
        vae=vae,
        text_encoder=te,
        tokenizer=tok,
        unet=unet,
        scheduler=sched,
        safety_checker=None,
        feature_extractor=None,
        requires_safety_checker=False,
    )
    out = root / "sd2"
    pipe.save_pretrained(out)
    return out


@pytest.fixture(scope="module")
def tiny_sd2(tmp_path_factory):
    return _tiny_pipeline(tmp_path_factory.mktemp("sd2"))


def _scene64():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 3, 64, 64, generator=g)
    mask = torch.zeros(1, 1, 64, 64)
    mask[..., 20:44, 16:40] = 1
    return img, mask


def test_loader_and_guided_unguided_steps(tiny_sd2):
    den = SD2Denoiser.from_pretrained(tiny_sd2)
    assert den.prediction_type == "v" and den.vae_factor == 2
    img, mask = _scene64()
    cond = den.make_condition(img, mask, "a bench")
    assert cond.mask.shape == (1, 1, 32, 32) and cond.masked_latent.shape == (1, 4, 32, 32)
    s = DDIMSampler(den, SamplerConfig(num_steps=3, guidance_scale=0.3))
    z = torch.randn(1, 4, 32, 32, generator=torch.Generator().manual_seed(1))
    target = torch.full((1, 3, 64, 64), 0.8)

    def energy(x):
        return ((x - target) ** 2).mean()

    zu, x0u, _ = s.step(z, 2, cond)
    zg, x0g, e = s.step(z, 2, cond, energy=energy)
    assert torch.isfinite(zu).all() and torch.isfinite(zg).all() and e is not None
    assert torch.equal(x0u, x0g)  # same prediction; only the guidance step differs
    assert (zg - zu).abs().max() > 0  # non-zero guidance gradient through UNet and VAE decoder
    # the gradient itself, w.r.t. z_t through the denoiser and decoder
    zr = z.clone().requires_grad_(True)
    from coin_cl.diffusion.sampling import split_prediction

    x0, _ = split_prediction(den.predict(zr, torch.tensor([int(s.timesteps[2])]), cond), zr, s.a[2], "v")
    (g,) = torch.autograd.grad(energy(den.decode(x0)), zr)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_inpaint_paste_back_keeps_outside(tiny_sd2):
    den = SD2Denoiser.from_pretrained(tiny_sd2)
    img = np.random.default_rng(0).random((64, 80, 3)).astype(np.float32)
    mask = np.zeros((64, 80), bool)
    mask[10:30, 50:80] = True  # touches the right border
    cfg = InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=3, cfg_scale=2.0))
    out, source = inpaint_image(img, mask, sd2=den, cfg=cfg, prompt="a", seed=0)
    assert source == "Stable Diffusion 2 inpainting"
    assert np.isfinite(out).all() and out.dtype == np.float32
    assert np.array_equal(out[~mask], img[~mask])
    assert not np.array_equal(out[mask], img[mask])
    # guided (energy on the decoded crop pulls the fill toward white): still only the mask changes
    gcfg = InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=3, guidance_scale=0.5))
    gout, _ = inpaint_image(img, mask, sd2=den, cfg=gcfg, seed=0, energy=lambda x: ((x - 1) ** 2).mean())
    uout, _ = inpaint_image(
        img, mask, sd2=den, cfg=InpaintConfig(sd_crop=64, sampler_sd=SamplerConfig(num_steps=3)), seed=0
    )
    assert np.isfinite(gout).all() and np.array_equal(gout[~mask], img[~mask])
    assert gout[mask].mean() > uout[mask].mean()  # the energy's direction


def test_missing_file_is_named(tiny_sd2, tmp_path, monkeypatch):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(tiny_sd2, broken)
    (broken / "vae" / "diffusion_pytorch_model.safetensors").unlink()
    assert any("vae/diffusion_pytorch_model.safetensors" in m for m in missing_sd2_files(broken))
    with pytest.raises(FileNotFoundError, match=r"vae/diffusion_pytorch_model\.safetensors.*--sd-path"):
        SD2Denoiser.from_pretrained(broken)
    (broken / "tokenizer" / "tokenizer.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"tokenizer/vocab\.json"):
        check_sd2_folder(broken)
    monkeypatch.delenv("COIN_SD2_PATH", raising=False)
    with pytest.raises(FileNotFoundError, match="COIN_SD2_PATH"):
        check_sd2_folder(None)
    monkeypatch.setenv("COIN_SD2_PATH", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match="nowhere"):
        check_sd2_folder(None)


def test_available_models_reports_why(tiny_sd2, tmp_path, monkeypatch):
    from coin_cl import diffusion

    monkeypatch.delenv("COIN_SD2_PATH", raising=False)
    monkeypatch.delenv("COIN_DINO_WEIGHTS", raising=False)
    monkeypatch.delenv("COIN_LAMA_PATH", raising=False)
    r = diffusion.available_models()
    assert set(r) == {"sd2", "lama", "dino", "scene_prior"}
    assert not r["lama"]["available"] and "COIN_LAMA_PATH" in r["lama"]["reason"]
    assert not r["sd2"]["available"] and "COIN_SD2_PATH" in r["sd2"]["reason"]
    assert not r["dino"]["available"] and "analytic" in r["dino"]["reason"]
    assert r["scene_prior"]["available"]
    monkeypatch.setenv("COIN_SD2_PATH", str(tiny_sd2))
    monkeypatch.setenv("COIN_DINO_WEIGHTS", str(tmp_path / "missing.pth"))
    r = diffusion.available_models(prior_cache_dir=tmp_path)
    assert r["sd2"]["available"] and "complete" in r["sd2"]["reason"]
    assert not r["dino"]["available"] and "does not exist" in r["dino"]["reason"]
    assert "0 cached" in r["scene_prior"]["reason"]
    r = diffusion.available_models(sd2_path=tmp_path)
    assert not r["sd2"]["available"] and "unet/config.json" in r["sd2"]["reason"]


def test_package_never_imports_opencl():
    import subprocess
    import sys

    code = (
        "import sys, coin_cl.diffusion; "
        "print([m for m in sys.modules if m.startswith(('pyopencl', 'coin_cl.engine', 'coin_cl.pipeline'))])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
