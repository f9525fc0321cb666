"""Helpers shared by the op modules."""

from __future__ import annotations

import numpy as np

i32 = np.int32
f32 = np.float32


def groups(n: int, local: int = 64) -> int:
    """Global size: n rounded up to a multiple of the work-group size (at least one group)."""
    return max(local, (n + local - 1) // local * local)
