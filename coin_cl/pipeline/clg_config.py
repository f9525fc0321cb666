"""Settings of the CLG stage (CoIn paper 4.3 and supplement): the sampler's (a nested
`coin_cl.diffusion.SamplerConfig` with CLG's defaults), the energy's and the output's."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from coin_cl.diffusion.sampling import Denoiser, SamplerConfig

PAPER_STEPS = 200  # paper 4.3 / supplement: 200 'quad' DDIM steps with Stable Diffusion 2
DETAILS = ("reference", "input", "none")  # CLGConfig.detail (coin_cl.pipeline.clg_detail)
PRIOR_STEPS = 25  # the scene prior: a small pixel-space UNet on 2 cores, where 200 steps cost minutes a view


def clg_sampler() -> SamplerConfig:
    """CLG's sampler defaults (paper 4.3): 'quad' steps, FreeDoM's c = 0.5 over the first 80 % of
    the trajectory (the last steps only sharpen; guiding them fights the model for little
    consistency), time travel off. The step count is `CLGConfig.steps`."""
    return SamplerConfig(discretization="quad", guidance_scale=0.5, guidance_end=0.8)


@dataclass
class CLGConfig:
    """Settings of the CLG stage.

    steps: DDIM steps; None = PAPER_STEPS (200) for Stable Diffusion 2, PRIOR_STEPS (25) for the
        scene prior (the named smaller default: 200 steps of the prior cost minutes per view here).
    sampler: the DDIM sampler's settings (`coin_cl.diffusion.SamplerConfig`, defaults `clg_sampler`):
        discretization 'quad' (paper) or 'uniform', eta, FreeDoM's guidance_scale c (0 = unguided)
        and its window guidance_start/end, time travel (travel_repeats 1 = off), cfg_scale
        (classifier-free guidance, SD2 with a prompt only). Its num_steps is the step count when set
        to anything but SamplerConfig's default (50, which reads as unset): then it is `steps`
        (given both, they must agree); the count CLG uses is `steps` / `num_steps(denoiser)`.
    prompt: text (SD2 only). None (default): the run's (`CoInConfig.prompt`); "" = no text.
    alpha: position of the intermediate pose phi between k (0) and n (1) (paper 0.5).
    context: crop side >= context x the mask's bounding box side (as stage 1).
    w_hr, w_rgb: weights of the cosine and RGB terms of L3D (paper: 1 and 1).
    depth_tol, src_depth_tol, footprint: the warp op's knobs (see `coin_cl.engine.warp_features`).
    max_points: P_k is thinned to at most this many points (evenly by index) for speed; at the
        sampler's scale many points share a pixel anyway.
    feather_px: inward feather of the paste (outside the mask is untouched either way).
    seed: view n samples with seed + n. None (default): the run's seed (`CoInConfig.seed`; 0 outside a
        run); the resolved value is in log.json's 3_clg settings. progress: tqdm bars over views and steps.
    sample: False = no diffusion sampler: every hole pixel takes the energy's own target, the
        reference's colour warped through P_k where supported (S) and R_n elsewhere, i.e. the
        minimiser of E(X) with the RGB term alone (`warp_fill`). The pipeline uses it for an
        edited reference (`coin_cl.pipeline.insert`), where no model can draw the inserted object
        and a sampler would paint the hole with the scene's own textures.
    detail: where the output's band above the sampler's working resolution comes from
        (`coin_cl.pipeline.clg_detail`): "reference" (default) the reference's detail warped through
        P_k where the warp supports it and the initial inpaint's elsewhere, "input" the initial
        inpaint's everywhere, "none" the upsampled sample alone (blurry at 64 px: issue 22).
    detail_split: where the band split lies, as a share of the working size (0.5: the output's
        band above half the working resolution comes from `detail`'s source, below it from the
        guided sample).
    colour_match: match the Lab mean and deviation of the sample's low band inside the hole to the
        energy's target (the reference warped through P_k where supported, I^_n elsewhere), the gain
        capped at 1 (`clg_detail.match_colour`): the 64 px scene prior draws the reference's structure
        with drifting hues. Not applied with detail "none".
    chroma_from_target: with colour_match, the low band's chroma (Lab a, b) inside the hole is the
        target's own low band's and only its lightness comes from the sample (matched in mean and
        deviation): the global match left 64 px hue blotches in the accepted views.
    strength: the share of the trajectory sampled (SDEdit): 1 = from pure noise (paper); below 1
        the sampler starts from the initial inpaint's crop noised to that level, so what guidance
        does not constrain stays near I^_n instead of a fresh draw.
        Defaults (detail "reference", split 0.5, strength 0.5) measured on the shared scene's LaMa
        inpaints (benchmarks/clg.py, docs/RESULTS.md): the only variant whose images are closer to
        the reference than the inputs (residual lifted with the views' depths) while as textured;
        sampling from noise at 64 px and pasting (the paper's way at this size) lost to the input in
        29 of 33 views.
    keep_if_worse: a view's output must not be worse than its input I^_n on what can be measured
        without ground truth (issue 22): a larger consistency residual to the reference, less
        texture inside the mask (below (1 - texture_tol) x the input's), or colours further from the
        mask's surroundings (more than (1 + colour_tol) x the input's distance). Such a view keeps
        I^_n, logged and recorded with the reason (`coin_cl.pipeline.clg_guard.no_worse`).
    detail_gain_max: the detail band's top-up (`clg_detail.texture_gain`): a candidate whose texture
        inside the mask (`metrics.mask_texture`) falls below the input's gets its high band (the
        reference's warped detail, I^_n's elsewhere) multiplied by the smallest gain up to this that
        brings it back to the input's. Why: the warp resamples the reference's detail and loses
        some of it, and the sample's low band is smoother than I^_n's below the split, so an output
        closer to the reference came out a little less textured than its input (issue 22: 0.04 % /
        0.8 % on the shared scene). 1 = off. The gain is recorded per view ("detail_gain").
    warp_guard: keep_if_worse also for the warp-only fill (sample False). Off by default because
        that fill's main use is an edited reference, whose warp adds an object with colours and
        texture its surroundings lack (the colour check would reject exactly what was asked for);
        SD2's reference_only mode turns it on: there the warp replaces an embedded fill with the
        reference's content and must pass the same checks as a guided sample.
    """

    steps: int | None = None
    sampler: SamplerConfig = field(default_factory=clg_sampler)
    prompt: str | None = None
    alpha: float = 0.5
    context: float = 1.5
    w_hr: float = 1.0
    w_rgb: float = 1.0
    depth_tol: float = 0.01
    src_depth_tol: float = 0.01
    footprint: str = "bilinear"
    max_points: int = 400_000
    feather_px: int = 2
    seed: int | None = None
    progress: bool = True
    sample: bool = True
    detail: str = "reference"
    detail_split: float = 0.5
    colour_match: bool = True
    chroma_from_target: bool = True
    strength: float = 0.5
    keep_if_worse: bool = True
    warp_guard: bool = False
    texture_tol: float = 0.1
    detail_gain_max: float = 1.5
    colour_tol: float = 0.25

    def __post_init__(self) -> None:
        if self.detail not in DETAILS:
            raise ValueError(f"CLGConfig.detail must be one of {', '.join(DETAILS)}, got {self.detail!r}")
        if not 0.0 < self.detail_split <= 1.0:
            raise ValueError(f"CLGConfig.detail_split must be in (0, 1], got {self.detail_split}")
        if not (math.isfinite(self.detail_gain_max) and self.detail_gain_max >= 1.0):
            raise ValueError(
                f"CLGConfig.detail_gain_max must be a finite gain >= 1 (1 = off), got {self.detail_gain_max}"
            )
        if not 0.0 < self.strength <= 1.0:
            raise ValueError(f"CLGConfig.strength must be in (0, 1], got {self.strength}")
        n = self.sampler.num_steps
        if n != SamplerConfig().num_steps:
            if self.steps is None:
                self.steps = n  # the sampler's count, set: it is the step count
            elif self.steps != n:
                raise ValueError(f"CLGConfig.steps is {self.steps} and CLGConfig.sampler.num_steps {n}: "
                                 "give one of them (steps; None picks the model's default)")  # fmt: skip
        if self.steps is not None and not (isinstance(self.steps, int) and self.steps >= 1):
            raise ValueError(f"CLGConfig.steps is {self.steps!r}: give a step count >= 1, or None")
        self.sampler.validate()
        for name, ok, what in (
            ("alpha", 0.0 <= self.alpha <= 1.0, "in [0, 1]"),
            ("context", self.context >= 1.0, ">= 1"),
            ("w_hr", self.w_hr >= 0, ">= 0"),
            ("w_rgb", self.w_rgb >= 0, ">= 0"),
            ("depth_tol", self.depth_tol > 0, "> 0"),
            ("src_depth_tol", self.src_depth_tol > 0, "> 0"),
            ("max_points", self.max_points >= 1, ">= 1"),
            ("feather_px", self.feather_px >= 0, ">= 0"),
            ("texture_tol", 0.0 <= self.texture_tol < 1.0, "in [0, 1)"),
            ("colour_tol", self.colour_tol >= 0, ">= 0"),
        ):
            if not ok:
                raise ValueError(f"CLGConfig.{name} is {getattr(self, name)!r}: give a value {what}")
        if self.seed is not None and not (isinstance(self.seed, int) and not isinstance(self.seed, bool)):
            raise ValueError(f"CLGConfig.seed is {self.seed!r}: give an integer, or None for the run's seed")

    def num_steps(self, denoiser: Denoiser) -> int:
        if self.steps is not None:
            return int(self.steps)
        return PRIOR_STEPS if getattr(denoiser, "name", "") == "scene prior" else PAPER_STEPS

    def sampler_config(self, denoiser: Denoiser) -> SamplerConfig:
        """`sampler` with the step count for `denoiser`."""
        return replace(self.sampler, num_steps=self.num_steps(denoiser))
