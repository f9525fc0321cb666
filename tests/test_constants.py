"""kernels/common.h and coin_cl/engine/constants.py hold the same values."""

import re

from coin_cl.engine import constants
from coin_cl.engine.devices import kernel_dir

NAMES = [
    "TILE_SIZE", "NEAR_PLANE", "FAR_PLANE", "EPS2D", "ALPHA_THRESHOLD", "MAX_ALPHA",
    "TRANSMITTANCE_MIN", "ONE_MINUS_ALPHA_MIN", "SIGMA_RADIUS", "FRUSTUM_MARGIN", "EIGEN_FLOOR",
    "MAX_RADIUS_PX",
]  # fmt: skip


def test_header_matches_python():
    src = (kernel_dir() / "common.h").read_text()
    for name in NAMES:
        m = re.search(rf"#define {name} (.+)", src)
        assert m, f"{name} missing from common.h"
        expr = m.group(1).split("/*")[0].strip()
        value = eval(re.sub(r"(\d)f\b", r"\1", expr))  # C float literals -> Python
        assert abs(value - getattr(constants, name)) <= 1e-12 * abs(value), name
