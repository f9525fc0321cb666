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
    """Settings of the CLG stage; each field says what it means where it is declared. Values are
    checked here: a bad one is an error naming the field.

    Defaults of detail / detail_split / strength ("reference", 0.5, 0.5) measured on the shared
    scene's LaMa inpaints (benchmarks/clg.py, docs/RESULTS.md): the only variant whose images are
    closer to the reference than the inputs (residual lifted with the views' depths) while as
    textured; sampling from noise at 64 px and pasting (the paper's way at this size) lost to the
    input in 29 of 33 views."""

    # DDIM steps (>= 1). None (default): PAPER_STEPS (200) for Stable Diffusion 2, PRIOR_STEPS (25)
    # for the scene prior (200 steps of the prior cost minutes per view here).
    steps: int | None = None
    # The DDIM sampler's settings (`coin_cl.diffusion.SamplerConfig`, defaults `clg_sampler`):
    # discretization 'quad' (paper) or 'uniform', eta, FreeDoM's guidance_scale c (0 = unguided)
    # and its window guidance_start/end, time travel (travel_repeats 1 = off), cfg_scale
    # (classifier-free guidance, SD2 with a prompt only). Its num_steps, when set to anything but
    # SamplerConfig's default (50, which reads as unset), is the step count: then it is `steps`
    # (given both, they must agree).
    sampler: SamplerConfig = field(default_factory=clg_sampler)
    # Text (SD2 only). None (default): the run's (`CoInConfig.prompt`); "" = no text.
    prompt: str | None = None
    # Position of the intermediate pose phi between k (0) and n (1), in [0, 1]. Default 0.5: the paper's.
    alpha: float = 0.5
    # Crop side >= context x the mask's bounding-box side (>= 1). Default 1.5: as stage 1.
    context: float = 1.5
    # Weight of L3D's cosine term (>= 0). Default 1: the paper's.
    w_hr: float = 1.0
    # Weight of L3D's RGB term (>= 0). Default 1: the paper's.
    w_rgb: float = 1.0
    # The warp op's depth tolerance, relative (> 0; `coin_cl.engine.warp_features`).
    depth_tol: float = 0.01
    # The warp op's source-depth tolerance, relative (> 0; `coin_cl.engine.warp_features`).
    src_depth_tol: float = 0.01
    # The warp op's footprint (`coin_cl.engine.warp_features`, which checks the name).
    footprint: str = "bilinear"
    # P_k is thinned to at most this many points (evenly by index; >= 1) for speed: at the sampler's
    # scale many points share a pixel anyway.
    max_points: int = 400_000
    # Inward feather of the paste, px (>= 0; outside the mask is untouched either way).
    feather_px: int = 2
    # View n samples with seed + n. None (default): the run's seed (`CoInConfig.seed`; 0 outside a
    # run); the resolved value is in log.json's 3_clg settings.
    seed: int | None = None
    # tqdm bars over views and steps.
    progress: bool = True
    # False = no diffusion sampler: every hole pixel takes the energy's own target, the reference's
    # colour warped through P_k where supported (S) and R_n elsewhere, i.e. the minimiser of E(X) with
    # the RGB term alone (`warp_fill`). The pipeline sets it without Stable Diffusion 2 unless
    # `prior_sampler` asks (`coin_plan.clg_samples`; CLG then runs only with `without_sampler`) and in
    # SD2's reference_only mode.
    sample: bool = True
    # Where the output's band above the sampler's working resolution comes from, from DETAILS
    # (`coin_cl.pipeline.clg_detail`): "reference" (default; class docstring) the reference's detail
    # warped through P_k where the warp supports it and the initial inpaint's elsewhere, "input" the
    # initial inpaint's everywhere, "none" the upsampled sample alone (blurry at 64 px).
    detail: str = "reference"
    # Where the band split lies, as a share of the working size, in (0, 1] (0.5: the band above half
    # the working resolution comes from `detail`'s source, below it from the guided sample).
    detail_split: float = 0.5
    # Match the Lab mean and deviation of the sample's low band inside the hole to the energy's target
    # (the reference warped through P_k where supported, I^_n elsewhere), the gain capped at 1
    # (`clg_detail.match_colour`): the 64 px scene prior draws the reference's structure with
    # drifting hues. Not applied with detail "none".
    colour_match: bool = True
    # With colour_match, the low band's chroma (Lab a, b) inside the hole is the target's own low
    # band's and only its lightness comes from the sample: the global match left 64 px hue blotches.
    chroma_from_target: bool = True
    # The share of the trajectory sampled (SDEdit), in (0, 1]: 1 = from pure noise (paper); below 1
    # the sampler starts from the initial inpaint's crop noised to that level, so what guidance does
    # not constrain stays near I^_n instead of a fresh draw. Default 0.5 (class docstring).
    strength: float = 0.5
    # A view's output must not be worse than its input I^_n on what can be measured without ground
    # truth: a larger consistency residual to the reference, less texture inside the mask (below
    # (1 - texture_tol) x the input's), or colours further from the mask's surroundings (more than
    # (1 + colour_tol) x the input's distance); such a view keeps I^_n, logged with the reason
    # (`coin_cl.pipeline.clg_guard.no_worse`).
    keep_if_worse: bool = True
    # Without a sampler (`sample` False): the reference warped into view n's hole is blended in the
    # gradient domain against view n's own surroundings (True, `clg_view.propagated`,
    # `coin_cl.diffusion.poisson.poisson_blend`: the reference's texture in view n's light and
    # exposure, no seam) or pasted as it is (False: for an object that must keep its own colours).
    propagate: bool = True
    # Without Stable Diffusion 2, CLG samples with the embedded scene prior (True: the paper's guided
    # sampler on a 64 px model trained on the scene's own pixels, minutes of training) or, by default
    # (False), runs no sampler, and then runs only where `without_sampler` asks. With SD2 the sampler
    # is SD2. Measured: docs/history/RESULTS-2026.md, "CLG with and without the scene prior's sampler"
    # (the exemplar's fills), docs/BENCHMARKS.md, "CLG's sampler on learned fills" (SPIn-NeRF's LaMa fills).
    prior_sampler: bool = False
    # What CLG does when no sampler runs (no SD2, `prior_sampler` False): True = every view's hole
    # takes the reference's answer propagated (`propagate`), kept only where it is no worse than the
    # view's initial inpaint (`keep_if_worse` applies as `warp_guard`), on any stage-1 fills; False
    # (default) = CLG is left out, logged with the reason (`coin_plan.clg_skip_reason`), and TE-D
    # fits stage 1's images. Measured on two real scenes at two seeds each (docs/BENCHMARKS.md, "CLG
    # without a sampler against leaving it out"): the propagation lost m-PSNR and masked VGG distance
    # in all four pairs, the more the more views its guard let it write. SD2's reference_only mode
    # propagates whatever this says (its other views have no other source of the reference's answer).
    without_sampler: bool = False
    # keep_if_worse also for the warp-only fill (sample False). Off by default (a warp that adds
    # colours and texture its surroundings lack would be rejected by the colour check); the pipeline
    # turns it on whenever CLG runs without a sampler (`without_sampler`, SD2's reference_only mode).
    # An insertion runs no CLG (`coin_plan.clg_skip_reason`).
    warp_guard: bool = False
    # keep_if_worse's texture tolerance, a share in [0, 1).
    texture_tol: float = 0.1
    # The detail band's top-up (`clg_detail.texture_gain`), a gain >= 1 (1 = off): a candidate whose
    # texture inside the mask falls below the input's gets its high band multiplied by the smallest
    # gain up to this that brings it back (the warp resamples the reference's detail and loses some
    # of it); the propagated image without a sampler likewise (its band above half the view's size).
    # Recorded per view ("detail_gain").
    detail_gain_max: float = 1.5
    # keep_if_worse's colour tolerance, a share >= 0.
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
