"""Model choice of the stages (coin_cl.pipeline.models)."""

from __future__ import annotations

import pytest

from coin_cl.pipeline.models import sd2_denoiser


def test_no_weights_no_sd2(tmp_path):
    assert sd2_denoiser(None) is None and sd2_denoiser("") is None
    # a folder that is not an SD2 inpainting checkpoint is an error naming it, not a silent None
    with pytest.raises(Exception, match=str(tmp_path.name)):
        sd2_denoiser(str(tmp_path))
