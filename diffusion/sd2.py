"""Stable Diffusion 2 inpainting from a local diffusers-format folder (never downloads).

The folder is the one ``StableDiffusionInpaintPipeline.save_pretrained`` writes (for example a local
copy of stabilityai/stable-diffusion-2-inpainting): ``unet/``, ``vae/``, ``text_encoder/``,
``tokenizer/``, ``scheduler/``. It is named by an argument or the ``COIN_SD2_PATH`` environment variable
(the CLI's ``--sd-path``). Every part is loaded with ``local_files_only=True``; before that the folder is
checked and a missing file is named together with what to pass.

Conditioning is SD-inpainting's: the UNet sees 9 channels, [z_t (4), mask at latent size (1),
VAE latent of the masked image (4)]; the masked image is the image with the hole set to 0 in [-1, 1]
(grey), as the diffusers pipeline. Text: the prompt for insertion, the empty prompt for removal; with
``cfg_scale`` != 1 the empty prompt is the unconditional branch.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from .sampling import DDIMSampler, Denoiser, EnergyFn, SamplerConfig

log = logging.getLogger(__name__)

ENV_VAR = "COIN_SD2_PATH"
_WEIGHT_NAMES = {
    "unet": ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin"),
    "vae": ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin"),
    "text_encoder": ("model.safetensors", "pytorch_model.bin"),
}
_CONFIG_FILES = ("unet/config.json", "vae/config.json", "text_encoder/config.json")


def resolve_sd2_path(path: str | os.PathLike | None = None) -> Path | None:
    """The SD2 folder from the argument, else ``$COIN_SD2_PATH``; None when neither is given."""
    if path is not None:
        return Path(path)
    env = os.environ.get(ENV_VAR)
    return Path(env) if env else None


def missing_sd2_files(path: str | os.PathLike) -> list[str]:
    """Files a diffusers SD2-inpainting folder lacks (relative names; weights as 'a or b'); [] = complete."""
    root = Path(path)
    if not root.is_dir():
        return [f"{root} (the folder itself)"]
    missing = [f for f in _CONFIG_FILES if not (root / f).is_file()]
    for sub, names in _WEIGHT_NAMES.items():
        if not any((root / sub / n).is_file() for n in names):
            missing.append(" or ".join(f"{sub}/{n}" for n in names))
    # the tokenizer: the original repository ships vocab.json + merges.txt, a tokenizer saved by
    # transformers >= 5 a single tokenizer.json; either loads
    tok = root / "tokenizer"
    if not (tok / "tokenizer.json").is_file():
        missing += [f"tokenizer/{n}" for n in ("vocab.json", "merges.txt") if not (tok / n).is_file()]
    return missing


def check_sd2_folder(path: str | os.PathLike | None = None) -> Path:
    """Resolve and check the folder; raises FileNotFoundError naming the missing file and what to pass."""
    root = resolve_sd2_path(path)
    if root is None:
        raise FileNotFoundError(
            f"no Stable Diffusion 2 inpainting folder given: pass --sd-path DIR or set {ENV_VAR} to a "
            "diffusers-format copy of stable-diffusion-2-inpainting (nothing is downloaded)"
        )
    missing = missing_sd2_files(root)
    if missing:
        raise FileNotFoundError(
            f"Stable Diffusion 2 inpainting folder {root} is incomplete: missing {missing[0]}"
            + (f" (and {len(missing) - 1} more: {', '.join(missing[1:])})" if len(missing) > 1 else "")
            + f". Pass --sd-path / {ENV_VAR} pointing at a complete diffusers folder "
            "(StableDiffusionInpaintPipeline.save_pretrained layout)"
        )
    return root


@dataclass
class SD2Condition:
    """Per-batch conditioning: mask (B, 1, h, w) and masked_latent (B, 4, h, w) at latent size,
    text (B, 77, D) prompt embeddings."""

    mask: torch.Tensor
    masked_latent: torch.Tensor
    text: torch.Tensor


class SD2Denoiser(Denoiser):
    """SD2-inpainting as a :class:`Denoiser`: eps or v prediction as the scheduler config says.

    Images are (B, 3, H, W) float in [0, 1] with H, W multiples of the VAE factor (8 for SD);
    masks (B, 1, H, W), 1 = to fill.
    """

    name = "Stable Diffusion 2 inpainting"

    def __init__(
        self, unet: Any, vae: Any, text_encoder: Any, tokenizer: Any, prediction_type: str = "eps"
    ) -> None:
        if prediction_type not in ("eps", "v"):
            raise ValueError(f"prediction_type must be 'eps' or 'v', got {prediction_type!r}")
        if unet.config.in_channels != 9:
            raise ValueError(f"not an inpainting UNet: in_channels={unet.config.in_channels}, expected 9")
        self.unet, self.vae, self.text_encoder, self.tokenizer = unet, vae, text_encoder, tokenizer
        self.prediction_type = prediction_type
        self.scaling_factor = float(getattr(vae.config, "scaling_factor", 0.18215))
        self.vae_factor = 2 ** (len(vae.config.block_out_channels) - 1)
        self.latent_channels = int(vae.config.latent_channels)
        for m in (unet, vae, text_encoder):
            m.eval().requires_grad_(False)  # frozen: guidance needs grads w.r.t. z only

    @classmethod
    def from_pretrained(
        cls, path: str | os.PathLike | None = None, dtype: torch.dtype = torch.float32
    ) -> SD2Denoiser:
        """Load UNet, VAE, text encoder and tokenizer from a local folder (see module docstring)."""
        from diffusers import AutoencoderKL, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        root = check_sd2_folder(path)
        kw = {"local_files_only": True}
        unet = UNet2DConditionModel.from_pretrained(root, subfolder="unet", torch_dtype=dtype, **kw)
        vae = AutoencoderKL.from_pretrained(root, subfolder="vae", torch_dtype=dtype, **kw)
        te = CLIPTextModel.from_pretrained(root / "text_encoder", torch_dtype=dtype, **kw)
        tok = CLIPTokenizer.from_pretrained(root / "tokenizer", **kw)
        pt = "eps"
        sched = root / "scheduler" / "scheduler_config.json"
        if sched.is_file():
            kind = json.loads(sched.read_text()).get("prediction_type", "epsilon")
            pt = {"epsilon": "eps", "v_prediction": "v"}.get(kind)
            if pt is None:
                raise ValueError(
                    f"{sched}: prediction_type {kind!r} is not supported (epsilon, v_prediction)"
                )
        else:
            log.warning("%s has no scheduler/scheduler_config.json: assuming eps-prediction", root)
        log.info("Stable Diffusion 2 inpainting loaded from %s (%s-prediction)", root, pt)
        return cls(unet, vae, te, tok, pt)

    @torch.no_grad()
    def encode_prompt(self, prompt: str) -> torch.Tensor:
        """Text embeddings (1, 77, D) of a prompt ('' for removal)."""
        ids = self.tokenizer(
            prompt,
            padding="max_length",
            max_length=self.tokenizer.model_max_length,
            truncation=True,
            return_tensors="pt",
        ).input_ids
        return self.text_encoder(ids)[0]

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Image (B, 3, H, W) in [0, 1] -> latent (B, 4, H/f, W/f): the posterior mean, scaled."""
        dt = next(self.vae.parameters()).dtype
        return self.vae.encode((2 * x - 1).to(dt)).latent_dist.mean * self.scaling_factor

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent (B, 4, h, w) -> image (B, 3, h f, w f) in about [0, 1]; differentiable."""
        dt = next(self.vae.parameters()).dtype
        return (self.vae.decode((z / self.scaling_factor).to(dt)).sample + 1) / 2

    @torch.no_grad()
    def make_condition(self, image: torch.Tensor, mask: torch.Tensor, prompt: str = "") -> SD2Condition:
        """Conditioning for image (B, 3, H, W) in [0, 1] and mask (B, 1, H, W) (1 = fill)."""
        B, _, H, W = image.shape
        if H % self.vae_factor or W % self.vae_factor:
            raise ValueError(f"image size {H}x{W} is not a multiple of the VAE factor {self.vae_factor}")
        m = (mask > 0.5).to(image.dtype)
        masked = image * (1 - m) + 0.5 * m  # 0 in [-1, 1] inside the hole, as diffusers' pipeline
        lat = self.encode(masked)
        m_lat = F.interpolate(m, size=lat.shape[-2:], mode="nearest")
        text = self.encode_prompt(prompt).expand(B, -1, -1)
        return SD2Condition(m_lat.to(lat.dtype), lat, text)

    def predict(self, z: torch.Tensor, t: torch.Tensor, cond: Any = None) -> torch.Tensor:
        if not isinstance(cond, SD2Condition):
            raise TypeError("SD2Denoiser.predict needs an SD2Condition (see make_condition)")
        dt = next(self.unet.parameters()).dtype
        x = torch.cat([z, cond.mask, cond.masked_latent], dim=1).to(dt)
        return self.unet(x, t, encoder_hidden_states=cond.text.to(dt)).sample.to(z.dtype)

    def inpaint(
        self,
        image: torch.Tensor,
        mask: torch.Tensor,
        prompt: str = "",
        cfg: SamplerConfig | None = None,
        energy: EnergyFn | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Sample an inpainting of image (B, 3, H, W) [0, 1] under mask (B, 1, H, W); returns the decoded
        (B, 3, H, W) image in [0, 1] (whole crop; paste-back is the caller's, see inpaint2d)."""
        cfg = cfg or SamplerConfig(num_steps=50, discretization="uniform", cfg_scale=7.5)
        cond = self.make_condition(image, mask, prompt)
        uncond = None
        if cfg.cfg_scale != 1.0 and prompt:
            uncond = SD2Condition(cond.mask, cond.masked_latent, self.encode_prompt("").expand_as(cond.text))
        h, w = cond.mask.shape[-2:]
        z = torch.randn((image.shape[0], self.latent_channels, h, w), generator=generator)
        res = DDIMSampler(self, cfg).sample(z, cond, uncond, energy=energy, generator=generator)
        with torch.no_grad():
            return self.decode(res.z).clamp(0, 1)


# ----------------------------------------------------------------------------------------------
# Cost at the real size: the published configurations of stabilityai/stable-diffusion-2-inpainting
# (diffusers unet/config.json and vae/config.json, the fields that set the architecture), built with
# random weights by `benchmarks/inpaint2d.py --sd2` to time a step as a user with the weights waits.

SD2_UNET_CONFIG: dict = {
    "sample_size": 64,
    "in_channels": 9,  # z_t (4) + mask (1) + masked-image latent (4)
    "out_channels": 4,
    "down_block_types": [
        "CrossAttnDownBlock2D",
        "CrossAttnDownBlock2D",
        "CrossAttnDownBlock2D",
        "DownBlock2D",
    ],
    "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"],
    "block_out_channels": [320, 640, 1280, 1280],
    "layers_per_block": 2,
    "attention_head_dim": [5, 10, 20, 20],
    "cross_attention_dim": 1024,
    "use_linear_projection": True,
    "act_fn": "silu",
    "norm_num_groups": 32,
    "norm_eps": 1e-5,
    "flip_sin_to_cos": True,
    "freq_shift": 0,
    "downsample_padding": 1,
    "mid_block_scale_factor": 1,
    "center_input_sample": False,
}
SD2_VAE_CONFIG: dict = {
    "in_channels": 3,
    "out_channels": 3,
    "down_block_types": ["DownEncoderBlock2D"] * 4,
    "up_block_types": ["UpDecoderBlock2D"] * 4,
    "block_out_channels": [128, 256, 512, 512],
    "layers_per_block": 2,
    "latent_channels": 4,
    "norm_num_groups": 32,
    "act_fn": "silu",
    "sample_size": 512,
    "scaling_factor": 0.18215,
}
# Measured by `nice -n 15 python benchmarks/inpaint2d.py --sd2` (2 torch threads, float32, 512x512,
# see docs/BENCHMARKS.md for the machine): seconds per DDIM step and peak resident memory.
SD2_MEASURED = {"unguided_step_s": 43.3, "guided_step_s": 107.8, "peak_gib": 11.7, "threads": 2}


def build_sd2_random(seed: int = 0) -> tuple[Any, Any]:
    """(UNet2DConditionModel, AutoencoderKL) of SD2-inpainting's published sizes with random weights
    (same cost as the real ones; nothing loaded or downloaded)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel

    torch.manual_seed(seed)
    return UNet2DConditionModel(**SD2_UNET_CONFIG).eval(), AutoencoderKL(**SD2_VAE_CONFIG).eval()


def sd2_run_estimate(
    n_views: int, steps: int = 50, guided_views: int | None = None, measured: dict | None = None
) -> dict:
    """What an SD2 run costs on this CPU class, from the measured per-step figures: stage 1 samples
    every masked view unguided (`n_views` x `steps` unguided steps), CLG samples the non-reference
    views guided (`guided_views`, default n_views - 1, x `steps` guided steps: backprop through the
    UNet and the VAE decoder). Returns {"stage1_s", "clg_s", "total_s", "peak_gib", "message"};
    the seconds are None when no figures were measured."""
    m = {**SD2_MEASURED, **(measured or {})}
    gv = max(n_views - 1, 0) if guided_views is None else guided_views
    u, g = m.get("unguided_step_s"), m.get("guided_step_s")
    if u is None or g is None:
        return {"stage1_s": None, "clg_s": None, "total_s": None, "peak_gib": None,
                "message": "SD2 cost unknown: run benchmarks/inpaint2d.py --sd2"}  # fmt: skip
    s1, clg = n_views * steps * u, gv * steps * g
    msg = (
        f"SD2 at 512x512 on {m['threads']} CPU threads: ~{u:.0f} s per unguided step, ~{g:.0f} s per guided "
        f"step, peak ~{m['peak_gib']:.1f} GiB. Stage 1: {n_views} views x {steps} steps ~ {s1 / 3600:.1f} h; "
        f"CLG: {gv} views x {steps} guided steps ~ {clg / 3600:.1f} h; total ~ {(s1 + clg) / 3600:.1f} h"
    )
    return {"stage1_s": s1, "clg_s": clg, "total_s": s1 + clg, "peak_gib": m["peak_gib"], "message": msg}


def log_sd2_estimate(n_views: int, steps: int = 50, guided_views: int | None = None) -> dict:
    """Log `sd2_run_estimate` before an SD2 run starts (the pipeline calls this); returns it."""
    est = sd2_run_estimate(n_views, steps, guided_views)
    log.warning("%s", est["message"])
    return est
