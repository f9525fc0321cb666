"""Which diffusion model the stages use (CoIn paper 4.1 and 4.3): Stable Diffusion 2 inpainting when
its weights are given (`CoInConfig.sd_path`), else none here, and each stage falls back to the
scene's own prior (`coin_cl.diffusion.scene_prior`, trained by stage 1)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from coin_cl.diffusion.sd2 import SD2Denoiser


def sd2_denoiser(sd_path: str | None) -> SD2Denoiser | None:
    """The SD2 inpainting denoiser loaded from `sd_path` (a diffusers folder), None without one."""
    if not sd_path:
        return None
    from coin_cl.diffusion.sd2 import SD2Denoiser

    return SD2Denoiser.from_pretrained(sd_path)
