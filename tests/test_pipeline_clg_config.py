"""CLG's settings (coin_cl.pipeline.clg_config): the nested sampler's defaults, the step count by
model, and a sampler step count that would be ignored refused."""

from __future__ import annotations

from dataclasses import replace

import pytest
from coin_cl.diffusion.sampling import SamplerConfig

from coin_cl.pipeline.clg_config import PAPER_STEPS, PRIOR_STEPS, CLGConfig


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


def test_sampler_num_steps_is_refused():
    with pytest.raises(ValueError, match="CLGConfig.steps"):
        CLGConfig(sampler=SamplerConfig(num_steps=12))


@pytest.mark.parametrize("gain", [0.5, float("nan"), float("inf")])
def test_detail_gain_below_one_or_not_finite_is_refused(gain):
    with pytest.raises(ValueError, match="detail_gain_max"):
        CLGConfig(detail_gain_max=gain)
    assert CLGConfig(detail_gain_max=1.0).detail_gain_max == 1.0  # 1 = the top-up off
