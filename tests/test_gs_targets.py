"""Ref-GS targets (coin_cl.gs.targets): inpaint inside the mask, captured image outside."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from coin_cl.gs.targets import composite_targets


def test_composite_targets_numpy_and_torch():
    rng = np.random.default_rng(0)
    inp = rng.random((5, 6, 3), dtype=np.float32)
    img = rng.random((5, 6, 3), dtype=np.float32)
    m = np.zeros((5, 6), bool)
    m[1:3, 2:5] = True
    out = composite_targets(inp, img, m)
    assert np.array_equal(out[m], inp[m]) and np.array_equal(out[~m], img[~m])
    tout = composite_targets(torch.from_numpy(inp), torch.from_numpy(img), torch.from_numpy(m))
    assert isinstance(tout, torch.Tensor) and np.array_equal(tout.numpy(), out)
    with pytest.raises(ValueError, match="mask"):
        composite_targets(inp, img, m[:4])
    with pytest.raises(ValueError):
        composite_targets(inp, img[:4], m)
