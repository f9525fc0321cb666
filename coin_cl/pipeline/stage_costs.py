"""What the stages of a CoIn run cost in seconds, so that `--budget` holds all of them.

Two kinds of stage share a run's minutes (`coin_cl.pipeline.budget` applies the rule):

- *fixed* stages do a set amount of work per view (0_scene writes the views, 1_inpaint fills them,
  3_clg guides them, eval renders them; the scene prior trains a set step count). Their seconds are
  estimated before the run (`fixed_costs`) and subtracted from the budget;
- *GS* stages (0_refine's fit, Ref-GS, TE-D's two phases) train for a step count, which is chosen
  to fill what is left (`split_seconds`): each its fewest useful steps (MIN_STEPS) first, the rest
  by the stages' weights.

The per-view figures below were measured on the project's 2-core machine (AMD EPYC, Zen 3) on real
captures at budget 10 and are scaled to the machine at hand by the scene prior's probe (`machine_factor`:
these stages are torch-bound, as the prior is). They are estimates only: after every stage the
budget re-plans the GS stages still to come from the seconds the finished stages' manifests
record, so a fixed stage that runs over its estimate costs the later GS stages, not the budget.
"""

from __future__ import annotations

import math

# The view size the per-view figures below were measured at (cup_plain's 400x300). A view of P
# pixels costs (P / REFERENCE_PIXELS) ** exponent times its figure: the same scene at 800x600 (4x the
# pixels, quiet 2-core AMD EPYC Zen 4) took 3.7x the seconds a view in stage 1's exemplar fills (324 s
# against 91 s for 56 views), about 4x in CLG's propagation and eval's renders. CLG with its sampler
# draws at the scene prior's own 64-px size, so its figure is left unscaled (exponent 0).
REFERENCE_PIXELS = 400 * 300
# {stage: (seconds, seconds per view, the per-view figure's exponent of the view's pixels)} on the
# reference machine, without the scene prior's training. Measured at budget 10 on the cup_plain
# virtual-object scene (65 views of 400x300, 56 masked training views; scene prior probe 1.31 s/step,
# so these are its figures / 1.46): 0_scene 2.4 s, CLG's sampling 48 s of its 144 s (the rest the
# prior's 133 steps and the features), eval 34 s; a 71-view orbit capture's CLG took 2.4-4.4 min.
# Stage 1's exemplar fills, two views at a time on the 2 cores (`Inpaint2DConfig.workers`): 53 s
# for cup_plain's 56 views on a quiet AMD EPYC Zen 3 whose prior probe said 1.53 s/step, 0.47 s a
# view at the reference speed (0.5 taken); views filled from files (the dataset's own inpaints)
# are not counted (`coin_plan.fixed_views`).
FIXED_COSTS = {
    "0_scene": (1.0, 0.02, 1.0),
    "1_inpaint": (5.0, 0.5, 0.95),
    "3_clg": (10.0, 0.8, 0.0),
    "eval": (10.0, 0.2, 1.0),
    # CLG without a sampler (the reference warped and blended per view): 4.7 s for the 55 views
    "3_clg_propagate": (2.0, 0.1, 1.0),
}
# The stage an entry of FIXED_COSTS estimates, where the two names differ.
STAGE_OF = {"3_clg_propagate": "3_clg"}
# Eval's extra seconds per test view it also scores at the capture's size (renders at the photos'
# size, the masked metrics; `eval_stage.score_at_capture`), on the reference machine: the SPIn-NeRF
# scene's 5 views at 1008x567 added about 10 s besides their whole-image VGG distance, which that
# scoring leaves out. `fixed_views` gives their count as "eval_capture"; it is part of eval's estimate.
CAPTURE_SECONDS_PER_VIEW = 2.5
# The scene prior's seconds per step on the reference machine (133 steps in 120 s, the rate
# `diffusion.scene_prior.STEPS_PER_SECOND` was measured at): the fixed stages' figures are scaled by
# the measured prior rate over this one.
REFERENCE_PRIOR_SECONDS_PER_STEP = 120 / 133
# A scene prior step in a run costs this many probe steps: on a quiet 2-core AMD EPYC, 0.72-0.90 s a
# step in four runs (two scenes, budgets 5-20) against probes of 0.65-0.82 (1.23, 1.29, 0.88, 1.07:
# the probe's 2 timed steps are noisy); 1.15 is taken, and the re-plan after CLG gives TE-D what the
# estimate over-counted.
PRIOR_STEP_COST = 1.15
# The machine factor is kept within these bounds: a probe disturbed by a burst of load must not
# make a run plan for a machine 100x slower.
FACTOR_RANGE = (0.25, 8.0)
# The fewest steps that still make a GS stage worth its fixed costs (below them a fit is a blur):
# a budget that cannot give every budgeted stage these is refused with the minimum that can.
MIN_STEPS = {"refine": 100, "refgs": 100, "ted_finetune": 30, "ted_adversarial": 0}
# The order in which the stages run and spend the budget (`coin_cl.pipeline.config.STAGES`), with
# the GS stages by the plan's names.
STAGE_ORDER = ("0_scene", "0_refine", "1_inpaint", "2_refgs", "3_clg", "4_ted", "eval")
GS_STAGES = {"refine": "0_refine", "refgs": "2_refgs", "ted_finetune": "4_ted", "ted_adversarial": "4_ted"}


def machine_factor(prior_seconds_per_step: float | None) -> float:
    """How much slower than the reference machine this one runs the fixed stages: the scene
    prior's measured seconds per step over `REFERENCE_PRIOR_SECONDS_PER_STEP`, within FACTOR_RANGE;
    1.0 where the prior was not probed (SD2 runs, explicit counts)."""
    if prior_seconds_per_step is None:
        return 1.0
    if not math.isfinite(prior_seconds_per_step) or prior_seconds_per_step <= 0:
        raise ValueError(
            f"scene prior seconds per step must be a positive number, got {prior_seconds_per_step}"
        )
    lo, hi = FACTOR_RANGE
    return min(hi, max(lo, prior_seconds_per_step / REFERENCE_PRIOR_SECONDS_PER_STEP))


def fixed_costs(
    views: dict[str, int],
    factor: float,
    prior_steps: int | None = None,
    prior_seconds_per_step: float | None = None,
    view_pixels: int | None = None,
) -> dict[str, float]:
    """{stage: estimated seconds} of the fixed stages. views: {stage: the views it works on} for the
    stages the run has (0_scene and eval: every view; 1_inpaint and 3_clg: the masked training
    views; a stage left out is absent; "eval_capture": the test views eval also scores at the
    capture's size, added to eval's estimate); factor: `machine_factor`. "prior": the scene prior's
    training, `prior_steps` at its measured rate x PRIOR_STEP_COST (absent without a probed prior).
    view_pixels: a working view's pixels (the per-view figures scale with it, FIXED_COSTS' exponent;
    None: REFERENCE_PIXELS).

    >>> fixed_costs({"0_scene": 10, "eval": 10}, 2.0)
    {'0_scene': 2.4, 'eval': 24.0}
    >>> fixed_costs({"0_scene": 10, "eval": 10}, 2.0, view_pixels=4 * REFERENCE_PIXELS)
    {'0_scene': 3.6, 'eval': 36.0}
    """
    pixels = REFERENCE_PIXELS if view_pixels is None else int(view_pixels)
    if pixels < 1:
        raise ValueError(f"a view's pixels must be positive, got {view_pixels}")
    out = {}
    for stage, n in views.items():
        if stage == "eval_capture":
            continue
        base, per_view, exponent = FIXED_COSTS[stage]
        size = (pixels / REFERENCE_PIXELS) ** exponent
        out[STAGE_OF.get(stage, stage)] = factor * (base + per_view * size * max(0, int(n)))
    if "eval" in out:
        out["eval"] += factor * CAPTURE_SECONDS_PER_VIEW * max(0, int(views.get("eval_capture", 0)))
    if prior_steps is not None and prior_seconds_per_step is not None:
        out["prior"] = prior_steps * prior_seconds_per_step * PRIOR_STEP_COST
    return out


def split_seconds(
    pool: float, shares: dict[str, float], floors: dict[str, float] | None = None
) -> dict[str, float]:
    """{stage: seconds} of the GS stages from a pool of `pool` seconds: each stage with a share
    first gets its floor (`floors`, e.g. MIN_STEPS at its rate; none by default), the rest is split by
    the `shares` (relative weights; a stage with share 0 gets 0). A pool under the floors' sum
    scales them down; a negative one (the stages before overran) gives 0.

    >>> split_seconds(100.0, {"a": 1.0, "b": 3.0}, {"a": 20.0, "b": 0.0})
    {'a': 40.0, 'b': 60.0}
    """
    floors = {k: (floors or {}).get(k, 0.0) if s > 0 else 0.0 for k, s in shares.items()}
    need = sum(floors.values())
    pool = max(0.0, pool)
    if pool < need:
        return {k: f * pool / need for k, f in floors.items()}
    total = sum(shares.values())
    rest = pool - need
    return {k: floors[k] + (rest * s / total if total > 0 else 0.0) for k, s in shares.items()}


def min_floors(shares: dict[str, float], step_seconds: dict[str, float]) -> dict[str, float]:
    """{stage: seconds of its MIN_STEPS at `step_seconds`} for the stages with a share."""
    return {k: MIN_STEPS.get(k, 0) * step_seconds[k] for k, s in shares.items() if s > 0}


def minimum_pool(shares: dict[str, float], step_seconds: dict[str, float]) -> float:
    """The fewest seconds of GS training that give every stage with a share its MIN_STEPS at
    `step_seconds` ({stage: seconds per step})."""
    return sum(min_floors(shares, step_seconds).values())


def minimum_budget(
    fixed_seconds: float, prior_floor_seconds: float, prior_share: float, pool: float
) -> float:
    """The smallest budget in minutes that fits: `fixed_seconds` (the fixed stages and the probes,
    the prior's training left out), the prior's training (`prior_floor_seconds` at least, else
    `prior_share` of the budget) and a GS pool of `pool` seconds (`minimum_pool`).

    >>> round(minimum_budget(60.0, 120.0, 0.15, 120.0), 6)
    5.0
    """
    at_floor = (fixed_seconds + prior_floor_seconds + pool) / 60.0
    if prior_share * at_floor * 60.0 <= prior_floor_seconds or prior_share >= 1:
        return at_floor
    return (fixed_seconds + pool) / (60.0 * (1.0 - prior_share))
