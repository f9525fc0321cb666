"""Timing probes' one loop (pure stdlib, so `diffusion/` may use it): the run's plan measures a GS
step, a scene-prior step and TE-D's discriminator with it (`coin_cl.pipeline.budget`)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def step_seconds(step: Callable[[], object], steps: int, warmup: int) -> list[float]:
    """Wall seconds of each of `steps` calls of `step()`, timed on its own, after `warmup` untimed
    ones (kernel builds, first allocations). steps >= 1."""
    if steps < 1:
        raise ValueError(f"a timing probe needs at least one timed step, got {steps}")
    for _ in range(warmup):
        step()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return times


def mean_step_seconds(step: Callable[[], object], steps: int, warmup: int) -> float:
    """Mean of `step_seconds`."""
    return statistics.fmean(step_seconds(step, steps, warmup))


def median_step_seconds(step: Callable[[], object], steps: int, warmup: int) -> float:
    """Median of `step_seconds`: one call slowed by a burst of other work (a thread pool still
    winding down from the probe before, a page-fault storm) does not move it, as it moves a mean
    over few calls."""
    return statistics.median(step_seconds(step, steps, warmup))


def late_step_seconds(log: list[dict], share: float = 0.2) -> float | None:
    """Mean seconds per step over the last `share` of a training run, from a trainer's log entries
    ({"step", "train_seconds"}, in step order; the trainer writes one every few steps): what a step
    costs once the model has grown. None with fewer than two entries or a non-increasing record."""
    pts = [(int(e["step"]), float(e["train_seconds"])) for e in log
           if isinstance(e, dict) and isinstance(e.get("step"), int)
           and isinstance(e.get("train_seconds"), int | float)]  # fmt: skip
    if len(pts) < 2:
        return None
    last_step, last_s = pts[-1]
    start = next((p for p in pts if p[0] >= (1.0 - share) * last_step), pts[-2])
    if start[0] >= last_step:
        start = pts[-2]
    steps, seconds = last_step - start[0], last_s - start[1]
    if steps <= 0 or not seconds >= 0:
        return None
    return seconds / steps
