"""Timing probes' one loop (pure stdlib, so `diffusion/` may use it): the run's plan measures a GS
step, a scene-prior step and TE-D's discriminator with it (`coin_cl.pipeline.budget`)."""

from __future__ import annotations

import time
from collections.abc import Callable


def mean_step_seconds(step: Callable[[], object], steps: int, warmup: int) -> float:
    """Mean wall seconds of `steps` calls of `step()` after `warmup` untimed ones (kernel builds,
    first allocations). steps >= 1."""
    if steps < 1:
        raise ValueError(f"a timing probe needs at least one timed step, got {steps}")
    for _ in range(warmup):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return (time.perf_counter() - t0) / steps
