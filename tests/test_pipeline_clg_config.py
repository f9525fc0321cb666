"""CLG's settings (coin_cl.pipeline.clg_config): the nested sampler's defaults, the step count by
model, the sampler's own step count taken as the count, bad values refused naming the field."""

from __future__ import annotations

from dataclasses import replace

import pytest
from coin_cl.diffusion.sampling import SamplerConfig

from coin_cl.pipeline.clg_config import PAPER_STEPS, PRIOR_STEPS, CLGConfig, clg_sampler


class _Model:
    def __init__(self, name: str):
        self.name = name


def test_sampler_defaults_and_steps_by_model():
    cfg = CLGConfig()
    s = cfg.sampler
    assert (s.discretization, s.guidance_scale, s.guidance_start, s.guidance_end, s.travel_repeats) == (
        "quad", 0.5, 0.0, 0.8, 1
    )  # fmt: skip
    assert cfg.sampler_config(_Model("scene prior")).num_steps == PRIOR_STEPS
    assert cfg.sampler_config(_Model("Stable Diffusion 2 inpainting")).num_steps == PAPER_STEPS
    fixed = CLGConfig(steps=7, sampler=replace(s, guidance_scale=0.0, eta=0.3))
    out = fixed.sampler_config(_Model("scene prior"))
    assert (out.num_steps, out.guidance_scale, out.eta, out.discretization) == (7, 0.0, 0.3, "quad")
    assert fixed.sampler.num_steps == SamplerConfig().num_steps  # the config itself is not rewritten


def test_sampler_num_steps_is_the_step_count():
    """A step count set on the nested sampler is used (it is `steps`); given both, they must agree."""
    cfg = CLGConfig(sampler=replace(clg_sampler(), num_steps=12))
    assert cfg.steps == 12
    assert cfg.sampler_config(_Model("scene prior")).num_steps == 12
    assert cfg.sampler_config(_Model("Stable Diffusion 2 inpainting")).num_steps == 12
    assert CLGConfig(steps=12, sampler=replace(clg_sampler(), num_steps=12)).steps == 12
    with pytest.raises(ValueError, match="CLGConfig.steps .* CLGConfig.sampler.num_steps"):
        CLGConfig(steps=5, sampler=replace(clg_sampler(), num_steps=12))


@pytest.mark.parametrize(
    "change, named",
    [({"steps": 0}, "CLGConfig.steps"), ({"alpha": 1.5}, "CLGConfig.alpha"),
     ({"context": 0.5}, "CLGConfig.context"),
     ({"w_rgb": -1.0}, "CLGConfig.w_rgb"), ({"depth_tol": 0.0}, "CLGConfig.depth_tol"),
     ({"max_points": 0}, "CLGConfig.max_points"), ({"feather_px": -1}, "CLGConfig.feather_px"),
     ({"texture_tol": 1.0}, "CLGConfig.texture_tol"), ({"colour_tol": -0.1}, "CLGConfig.colour_tol"),
     ({"seed": 1.5}, "CLGConfig.seed"), ({"detail": "all"}, "CLGConfig.detail"),
     ({"strength": 0.0}, "CLGConfig.strength"), ({"sampler": SamplerConfig(eta=-1.0)}, "eta")],
)  # fmt: skip
def test_bad_values_are_refused_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named):
        CLGConfig(**change)


def test_seed_and_prompt_are_the_runs_unless_set():
    """None (the defaults) = the run's seed and prompt, resolved by `CoInConfig.clg_settings`, which is
    what the 3_clg stage key records; a value set here is used as given."""
    from coin_cl.pipeline.config import CoInConfig

    assert (CLGConfig().seed, CLGConfig().prompt) == (None, None)
    run = CoInConfig(seed=3, prompt="a vase")
    assert (run.clg_settings().seed, run.clg_settings().prompt) == (3, "a vase")
    own = CoInConfig(seed=3, prompt="a vase", clg=CLGConfig(seed=9, prompt=""))
    assert (own.clg_settings().seed, own.clg_settings().prompt) == (9, "")
    assert (CoInConfig().clg_settings().seed, CoInConfig().clg_settings().prompt) == (0, "")  # as before


@pytest.mark.parametrize("gain", [0.5, float("nan"), float("inf")])
def test_detail_gain_below_one_or_not_finite_is_refused(gain):
    with pytest.raises(ValueError, match="detail_gain_max"):
        CLGConfig(detail_gain_max=gain)
    assert CLGConfig(detail_gain_max=1.0).detail_gain_max == 1.0  # 1 = the top-up off
