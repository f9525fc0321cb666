"""The grain benchmark's premise figure (benchmarks/grain.py): how predictable a hole's surroundings
are along their orientation, on a known answer: straight lines (fully) and noise (not at all)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from coin_cl.diffusion.directional import DirectionalConfig  # noqa: E402
from grain import along_line_correlation  # noqa: E402


def _hole(H=80, W=96):
    m = np.zeros((H, W), bool)
    m[28:52, 36:60] = True
    return m


def test_straight_lines_are_predictable_along_them_and_noise_is_not():
    y, x = np.mgrid[0:80, 0:96].astype(np.float32)
    across = -x * np.sin(np.pi / 3) + y * np.cos(np.pi / 3)
    prof = np.random.default_rng(0).standard_normal(200)
    lines = 0.5 + 0.05 * np.interp(across, np.arange(-100, 100), prof)
    img = np.repeat(lines[..., None], 3, -1).astype(np.float32)
    [(coherence, rho)] = along_line_correlation(img, _hole(), DirectionalConfig())
    assert coherence > 0.9 and rho > 0.9
    noise = (0.5 + 0.05 * np.random.default_rng(1).standard_normal((80, 96, 3))).astype(np.float32)
    [(_, rho)] = along_line_correlation(noise, _hole(), DirectionalConfig())
    assert abs(rho) < 0.15
