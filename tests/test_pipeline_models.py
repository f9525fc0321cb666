"""Model choice of the stages (coin_cl.pipeline.models)."""

from __future__ import annotations

import pytest

from coin_cl.pipeline.models import sd2_denoiser


def test_no_weights_no_sd2(tmp_path):
    assert sd2_denoiser(None) is None and sd2_denoiser("") is None
    # a folder that is not an SD2 inpainting checkpoint is an error naming it, not a silent None
    with pytest.raises(Exception, match=str(tmp_path.name)):
        sd2_denoiser(str(tmp_path))


def test_sd2_mode_rule_follows_the_estimate():
    """'auto' is reference_only on a CPU when SD2 on every view is estimated above the threshold
    (the reason names the estimate and the threshold), 'all' below it or off the CPU; an explicit mode
    is kept; a typo is an error."""
    from coin_cl.diffusion.sd2 import sd2_run_estimate

    from coin_cl.pipeline.models import SD2_ALL_VIEWS_MAX_HOURS, resolve_sd2_mode

    mode, why = resolve_sd2_mode("auto", 34, 50, on_cpu=True, clg_steps=200)
    assert mode == "reference_only" and f"{SD2_ALL_VIEWS_MAX_HOURS:g} h" in why and "s per guided step" in why
    assert resolve_sd2_mode("auto", 34, 50, on_cpu=False, clg_steps=200)[0] == "all"
    assert resolve_sd2_mode("all", 34, 50, on_cpu=True)[0] == "all"
    assert resolve_sd2_mode("reference_only", 1, 1, on_cpu=False)[0] == "reference_only"
    # one view, one step: far below the threshold
    assert sd2_run_estimate(1, 1)["total_s"] < SD2_ALL_VIEWS_MAX_HOURS * 3600
    assert resolve_sd2_mode("auto", 1, 1, on_cpu=True)[0] == "all"
    with pytest.raises(ValueError, match="sd2_mode"):
        resolve_sd2_mode("reference", 1, 1, on_cpu=True)
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig

    with pytest.raises(ValueError, match="sd2_mode"):
        Inpaint2DConfig(sd2_mode="reference")
