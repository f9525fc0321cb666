"""The run's plan: working resolution and step counts from the minute budget.

`--budget B` is the run's wall-clock minutes, every stage included. CoIn's published schedule (10k
Ref-GS steps, 10k + 10k TE-D, paper supp. A) is far beyond 2 CPU cores, so a run is planned from
`B` on the machine at hand:

1. Working resolution (`working_resolution`): the image scale 1/n (n an integer) that brings a
   view to at most `MAX_WORK_PIXELS` pixels, whatever the budget (measured on the shared SPIn-NeRF
   scene at budget 30: at 1008x567 the budget buys ~280 Ref-GS steps and the result loses to the
   naive baseline, at 504x284 it buys ~700 and wins; on the cup capture scored at its photos' 800x600,
   400x300 beat 800x600 on every figure at budgets 10 and 30: docs/BENCHMARKS.md, "The working size
   on the curve"). `--resolution` overrides.
2. Probes: a plain Scaffold-GS trained on the scene's views for `PROBE_STEPS` steps, a few steps of
   the scene prior and of TE-D's discriminator measure this machine (~10-30 s; their own wall time
   is part of the budget and recorded).
3. The split (`plan_run`): from the budget's seconds come off, in this order, the probes, the
   fixed stages' estimates (`coin_cl.pipeline.stage_costs`: 0_scene, stage 1 and CLG per masked
   view, eval per view, scaled by the scene prior's measured rate) and the scene prior's training
   (`BUDGET_SHARES["prior"]` of the budget as seconds, never below the step count of
   `PRIOR_MIN_SECONDS`). What is left, the GS pool, is split between the GS stages by their weights
   (`BUDGET_SHARES`; 0_refine's fit gets `REFINE_SHARE` when the run refines its masks) and turned
   into steps with the measured cost of each stage relative to the probe's step (`STEP_COST`).
   A budget whose pool cannot give every GS stage `stage_costs.MIN_STEPS` is refused before any
   stage runs (`BudgetTooSmall`, a ValueError naming the minimum budget that fits here).
4. The re-plan (`coin_cl.pipeline.schedule`): when a GS stage is reached, its count is planned
   again from what is left: the budget minus the probes, minus the seconds the finished stages'
   manifests record, minus the estimates of the fixed stages still to come; shared with the GS
   stages after it by their weights. TE-D's steps are costed from Ref-GS's measured rate
   (`ted_step_seconds`). Every figure is a pure function of plan.json and the manifests already
   written, so a killed run resumes to the same schedule, and a stage's key changes only when its
   counts do.
   Ref-GS measures its own first steps before it trains and plans its count again from them
   (`refgs_steps_from_rate`, its growth included; the stage records the decision, so a rerun keeps it).
5. A safety cap: each GS stage also stops at `CAP_FACTOR` x its planned seconds (logged), so a
   machine much slower than its probe (another job starting) cannot run far over the budget.

`--iters` / `CoInConfig.iters_*` replace the plan's counts with fixed ones (their estimated seconds
still come off the pool of the others). The plan is written to `OUT/plan.json` and reused by every
rerun of the same settings.

TE-D's adversarial step is a fine-tune step plus its discriminator's cost, which its probe
measures (`ted.probe_discriminator_seconds`): that cost does not shrink with the images as a
GS step does, so a fixed ratio measured at 504x284 underplanned it 2.2x at 192x144.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from coin_cl.atomic import write_text
from coin_cl.pipeline import stage_costs as costs
from coin_cl.schema import MAX_STEPS, PLAN, SchemaError, parse, run_folder_fix
from coin_cl.timing import mean_step_seconds

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Scene

log = logging.getLogger(__name__)

# A view is brought to at most this many pixels by default (504x284 = 143k is the measured winner;
# see the module docstring). The scale is 1/n so that pixel grids stay aligned with the capture's.
MAX_WORK_PIXELS = 160_000
# "prior": the scene prior's share of the whole budget (as seconds of training); the rest: the
# weights by which the GS stages split the GS pool (what the budget leaves after the probes, the
# fixed stages and the prior; module doc).
BUDGET_SHARES = {"prior": 0.15, "refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.3}
# 0_refine's weight beside BUDGET_SHARES' GS weights, when the run refines its masks: its fit (a
# plain 3DGS on the captures) measured 2.5-5.5 min at budget 10 beside Ref-GS's 3.5 planned.
REFINE_SHARE = 0.15
# The GS stages a plan may hold, in the order they run.
GS_KEYS = ("refine", "refgs", "ted_finetune", "ted_adversarial")
# Mean seconds per step of each GS stage over a whole run, relative to the probe's plain Scaffold-GS
# step at the start of training (Ref-GS adds its terms and the model grows by densification; TE-D's
# adversarial phase renders patches for the discriminator). Ref-GS measured on SPIn-NeRF at 504x284
# (Zen 5, quiet machine; the default run of docs/RESULTS.md at 638718a): probe 0.236 s/step; Ref-GS
# 0.19-0.24 s/step over its first 100 steps (585k primitives), 0.7 s/step from step ~1000 (1.7M
# primitives, anchor attention on), 0.513 s/step on average over the 1535 steps its cap allowed of
# the 1668 planned at 1.6x: 2.2x the probe over a whole run; 1.95x on cup_plain at budget 10 (quiet
# Zen 3: probe 0.076, Ref-GS 0.148 s/step). TE-D's follow from Ref-GS's by TED_PER_REFGS_STEP
# (below) until Ref-GS has run; then TE-D is planned again from Ref-GS's measured late rate.
# 0_refine's fit (plain 3DGS, `RefineConfig.model`) at budget 10: 731 steps in 154 s on cup_plain
# (probe 0.13 s/step: 1.6x), up to 5.5 min on a 71-view orbit capture (about 3.5x); 2.5 is taken,
# and the re-plan after it gives the later GS stages what it did not use (or takes what it overran).
STEP_COST = {"refine": 2.5, "refgs": 2.2}
# A TE-D step's cost relative to a late Ref-GS step (the last fifth of its run: TE-D trains the
# model at its final size; `schedule.refgs_step_seconds`), measured in six full runs on the 2-core
# AMD EPYC (SPIn-NeRF at 504x284, a model that does not grow; the cup_plain virtual-object scene at
# 400x300, grown 2.5x; budgets 5-20): fine-tune 0.69-1.02 of the late step, 0.86 on average (against
# the mean step 0.78-1.11, 0.92 on average: the spread is the machine's, not the model's); the
# adversarial step (used where the discriminator was not probed) 1.22-1.24 on SPIn-NeRF. TE-D's
# counts are planned again from Ref-GS's measured rate once it has run (`schedule.stage_schedule`).
TED_PER_REFGS_STEP = {"ted_finetune": 0.86, "ted_adversarial": 1.23}
STEP_COST.update({k: STEP_COST["refgs"] * r for k, r in TED_PER_REFGS_STEP.items()})
# Ref-GS plans its count again from its own first steps (`refgs_steps_from_rate`), as the probe's
# plain model measured 0.67x (SPIn-NeRF: Ref-GS's pruned, masked model is cheaper) to 5x (two real
# captures: the model grows) of Ref-GS's mean step. Its step cost grows with the model's size to
# this power, and the model reaches its size cap early in the run, so the mean step is the grown
# one: cup_plain at budget 10, 52.8k -> 134k neural Gaussians (2.55x), first steps 0.077 s, mean
# 0.127, last fifth 0.150 (2.55^0.55 = 1.67: 0.129). A model that starts above its per-pixel cap
# may grow to Ref-GS's floor (`RefGSConfig.growth_over_initial`): SPIn-NeRF at budget 10 planned a
# mean step of 0.73 s from first steps of 0.58 s (553k -> 597k, late steps 1.0 s).
GROWTH_COST_EXPONENT = 0.55
PROBE_STEPS = 12  # timed steps, after PROBE_WARMUP untimed ones (kernel builds, first allocations)
PROBE_WARMUP = 3
CAP_FACTOR = 1.25
PRIOR_MIN_SECONDS = 120.0
PLAN_FILE = "plan.json"


def working_resolution(width: int, height: int, max_pixels: int = MAX_WORK_PIXELS) -> float:
    """The default image scale 1/n for a (width, height) capture: the largest with at most
    `max_pixels` pixels (1.0 when the capture is already that small).

    >>> working_resolution(1008, 567), working_resolution(192, 144), working_resolution(4032, 3024)
    (0.5, 1.0, 0.1111111111111111)
    """
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    n = math.ceil(math.sqrt(width * height / max_pixels))
    return 1.0 / max(1, n)


@dataclass(frozen=True)
class Plan:
    """What each stage is given, as planned before any stage ran (each GS stage is planned again
    when reached: `schedule.stage_schedule`). steps: {"refgs", "ted_finetune", "ted_adversarial", and
    "refine" (0_refine's fit) in a run that refines its masks} -> steps; minutes: the planned
    minutes of each (None where counts were given explicitly); prior_seconds:
    the scene prior's training; probe_seconds_per_step: the probe's figure (None: no probe);
    source: "probe" or "explicit"; key: the settings the plan was made for (a rerun with the same
    key reuses it); prior_steps: the scene prior's step count, from `prior_seconds` at the rate its
    own probe measured on this machine (`prior_seconds_per_step`; None: no probe, the fixed 2-core
    rate of `diffusion.scene_prior.steps_for_seconds` applies); disc_seconds_per_step: what TE-D's
    discriminator adds to an adversarial step here (`ted.probe_discriminator_seconds`; None: the
    fixed ratio `TED_PER_REFGS_STEP` applies)."""

    steps: dict[str, int]
    minutes: dict[str, float | None]
    prior_seconds: float
    probe_seconds_per_step: float | None
    source: str
    key: dict[str, Any]
    prior_steps: int | None = None
    prior_seconds_per_step: float | None = None
    disc_seconds_per_step: float | None = None
    # The budget's shares this plan split (None: BUDGET_SHARES): a run without TE-D's adversarial
    # phase gives its share to the fine-tune phase, a run that refines its masks adds "refine"
    # (`coin_plan.plan_for`).
    shares: dict[str, float] | None = None
    # {stage: estimated seconds} of the fixed stages ("0_scene", "1_inpaint", "3_clg", "eval",
    # "prior": the scene prior's training; `stage_costs.fixed_costs`); None: none estimated.
    fixed_seconds: dict[str, float] | None = None
    # The probes' own wall time, measured when the plan was made (a plan taking another run's rates
    # takes its figure too); None: no probe ran.
    probe_wall_seconds: float | None = None

    def cap_seconds(self, stage: str) -> float:
        """The safety cap of a GS stage (0: none, for explicit step counts)."""
        m = self.minutes.get(stage)
        return 0.0 if m is None else CAP_FACTOR * 60.0 * m

    def describe(self) -> str:
        parts = []
        for k, n in self.steps.items():
            m = self.minutes.get(k)
            parts.append(f"{k} {n} steps" + ("" if m is None else f" (~{m:.1f} min)"))
        return ", ".join(parts) + ", " + prior_text(asdict(self))


def prior_text(plan: dict[str, Any]) -> str:
    """What a plan (`Plan` as a dict, plan.json's form) gives the scene prior, for logs and reports:
    "scene prior S s (N steps)", or "no scene prior trained" where no stage trains one (its steps
    are still planned: stage 1's key holds them)."""
    fixed = plan.get("fixed_seconds")
    if fixed is not None and "prior" not in fixed:
        return "no scene prior trained"
    steps = "" if plan.get("prior_steps") is None else f" ({plan['prior_steps']} steps)"
    return f"scene prior {plan.get('prior_seconds', 0):.0f} s{steps}"


# A recorded plan's probe-planned step count may exceed what its own recorded rate gives by this factor
# (the cost constants above may be re-measured between versions); beyond it the file was not made
# by `plan_run`.
PLAN_SLACK = 4.0


def read_plan(path: Path) -> Plan:
    """The plan in `path` (a run folder's plan.json), checked: the schema (`coin_cl.schema.PLAN`), and
    step counts that `plan_run` could have made: an explicit count equal to the one its key records,
    a probe-planned one at most PLAN_SLACK x what its budget at its recorded rate gives. Anything
    else is a `SchemaError` naming the file and the field (a planted plan asking for 10^9 steps is
    refused, not obeyed)."""
    fix = run_folder_fix(path, "the next run plans again")
    doc = parse(path, PLAN, fix)
    plan = Plan(**doc)
    explicit = plan.key.get("explicit")
    for i, k in enumerate(GS_KEYS):
        if k not in plan.steps:  # "refine": only in a plan of a run that refines its masks
            continue
        n, minutes = plan.steps[k], plan.minutes.get(k)
        given = explicit[i - 1] if isinstance(explicit, list) and len(explicit) == 4 and i else None
        if minutes is None:  # an explicit count
            if given is not None and n != given:
                raise SchemaError(f"{path}: steps.{k} is {n} but key.explicit gives {given}; {fix}")
            continue
        spp = plan.probe_seconds_per_step
        if spp is None:
            raise SchemaError(f"{path}: steps.{k} was planned from minutes.{k} but "
                              f"probe_seconds_per_step is null; {fix}")  # fmt: skip
        most = max(1, int(PLAN_SLACK * minutes * 60.0 / (spp * STEP_COST[k])) + 1)
        if n > most:
            raise SchemaError(f"{path}: steps.{k} is {n}, more than {minutes:g} minutes at {spp:.4g} s/step "
                              f"could plan (at most {most}); {fix}")  # fmt: skip
    if plan.prior_steps is not None and plan.prior_seconds_per_step is not None:
        from coin_cl.diffusion.scene_prior import steps_for_seconds

        floor = steps_for_seconds(PRIOR_MIN_SECONDS)  # the minimum's steps at the fixed 2-core rate
        most = int(PLAN_SLACK * max(plan.prior_seconds / plan.prior_seconds_per_step, floor)) + 1
        if plan.prior_steps > most:
            raise SchemaError(
                f"{path}: prior_steps is {plan.prior_steps}, more than {plan.prior_seconds:g} s "
                f"at {plan.prior_seconds_per_step:.4g} s/step could plan (at most {most}); "
                f"{fix}"
            )
    return plan


def steps_from_rate(
    pool_minutes: float, seconds_per_step: float, shares: dict[str, float] | None = None
) -> tuple[dict[str, int], dict[str, float]]:
    """({stage: steps}, {stage: minutes}) of the GS stages for a GS pool of `pool_minutes` at a probe
    rate: each stage gets the pool's part its weight in `shares` gives (default BUDGET_SHARES;
    "refine" only where `shares` has it) divided by its cost. Monotone: more minutes or a faster
    machine never give fewer steps. At least 1 Ref-GS step; TE-D may get 0 (then it passes Ref-GS
    through, logged)."""
    if not math.isfinite(seconds_per_step) or seconds_per_step <= 0:
        raise ValueError(f"probe seconds per step must be a positive number, got {seconds_per_step}")
    if not math.isfinite(pool_minutes) or pool_minutes <= 0:
        raise ValueError(f"budget must be a positive number of minutes, got {pool_minutes}")
    weights = gs_weights(shares)
    floors = costs.min_floors(weights, {k: seconds_per_step * STEP_COST[k] for k in weights})
    split = costs.split_seconds(60.0 * pool_minutes, weights, floors)
    minutes = {k: split[k] / 60.0 for k in weights}
    steps = {k: stage_steps(k, minutes[k], seconds_per_step) for k in weights}
    if "refgs" in steps:
        steps["refgs"] = max(1, steps["refgs"])
    return steps, minutes


def gs_weights(shares: dict[str, float] | None) -> dict[str, float]:
    """{GS stage: weight} of `shares` (default BUDGET_SHARES), in GS_KEYS order; "refine" only where
    `shares` names it."""
    shares = shares or BUDGET_SHARES
    return {k: float(shares[k]) for k in GS_KEYS if k in shares}


def stage_steps(stage: str, minutes: float, seconds_per_step: float) -> int:
    """Steps of GS stage `stage` ("refgs", "ted_finetune", "ted_adversarial") in `minutes` at the
    probe's `seconds_per_step`: the stage's step costs STEP_COST[stage] probe steps."""
    return int(minutes * 60.0 / (seconds_per_step * STEP_COST[stage]))


def refgs_steps_from_rate(
    seconds: float, first_seconds_per_step: float, size: int, limit: int
) -> tuple[int, float]:
    """(steps, mean seconds per step) of a Ref-GS run given `seconds` of training, from the seconds
    per step of its first steps at `size` primitives and the size its growth may reach (`limit`,
    `Strategy.size_limit`; 0: unknown, taken as no growth). The mean step costs the first times
    (limit / size) ^ GROWTH_COST_EXPONENT (at least 1): the model grows to its cap early. At least
    `stage_costs.MIN_STEPS["refgs"]` steps (the plan gave the stage its floor's minutes), at most
    MAX_STEPS. Monotone: more seconds or a faster step never give fewer steps."""
    if not (math.isfinite(first_seconds_per_step) and first_seconds_per_step > 0):
        raise ValueError(f"seconds per step must be a positive number, got {first_seconds_per_step}")
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"Ref-GS's seconds must be a finite number >= 0, got {seconds}")
    growth = max(1.0, limit / size) ** GROWTH_COST_EXPONENT if size > 0 and limit > 0 else 1.0
    mean = first_seconds_per_step * growth
    return min(MAX_STEPS, max(costs.MIN_STEPS["refgs"], int(seconds / mean))), mean


def standalone_steps(stage: str, minutes: float | None, iters: int | None, probe: Callable[[], float]) -> int:
    """The schedule of one GS stage run on its own (e.g. `pipeline.refgs.run_refgs`): `iters` when
    given; else `minutes` of that stage at the rate `probe()` measures (seconds per probe step, see
    `probe_seconds_per_step`), by `stage_steps`, the pipeline's rule (at least 1); else the
    published schedule (`REFERENCE_ITERS`, 30k)."""
    from coin_cl.gs.model_kinds import REFERENCE_ITERS

    if iters is not None:
        if iters < 1:
            raise ValueError(f"iters must be >= 1, got {iters}")
        return int(iters)
    if minutes is None:
        return REFERENCE_ITERS
    if not math.isfinite(minutes) or minutes <= 0:
        raise ValueError(f"budget_minutes must be > 0, got {minutes}")
    spp = float(probe())
    if not math.isfinite(spp) or spp <= 0:
        raise ValueError(f"probe seconds per step must be a positive number, got {spp}")
    n = max(1, stage_steps(stage, minutes, spp))
    log.info("%s: %.1f min at the probe's %.3f s/step x %.2f -> %d steps", stage, minutes, spp,
             STEP_COST[stage], n)  # fmt: skip
    return n


def prior_seconds(budget_minutes: float) -> float:
    """The scene prior's training seconds under the budget (never below PRIOR_MIN_SECONDS)."""
    return max(PRIOR_MIN_SECONDS, 60.0 * BUDGET_SHARES["prior"] * budget_minutes)


def probe_seconds_per_step(
    scene: Scene, train_idx: list[int], device: DeviceLike = None, seed: int = 0
) -> float:
    """Seconds per step of a plain Scaffold-GS trained on `scene`'s captured training views (the
    model every GS stage of CoIn trains), measured over PROBE_STEPS steps after PROBE_WARMUP.
    The model is thrown away."""
    from coin_cl.gs.data import init_points, scene_extent, views_from_scene
    from coin_cl.gs.model_kinds import build_model, scaled_model_config, scaled_strategy
    from coin_cl.gs.trainer import TrainConfig, Trainer

    n = PROBE_WARMUP + PROBE_STEPS
    views = views_from_scene(scene, train_idx)
    pts, cols = init_points(scene, views)
    # The probe trains on a schedule as long as a real run's, so no densification event falls in it.
    long = 1000
    model = build_model("scaffold", pts, cols, scene_extent([v.camera for v in views]), seed,
                        scaled_model_config("scaffold", long))  # fmt: skip
    model.device = device
    cfg = TrainConfig(model="scaffold", iters=n, seed=seed, progress=False, ckpt_every=0, export_ply=False)
    with tempfile.TemporaryDirectory(prefix="coin-cl-probe-") as tmp:
        tr = Trainer(model, views, [], cfg, Path(tmp), strategy=scaled_strategy("scaffold", long))

        def step() -> None:
            tr.train_step()
            tr.step += 1

        return mean_step_seconds(step, PROBE_STEPS, PROBE_WARMUP)


class BudgetTooSmall(ValueError):
    """A budget that cannot fit the run on this machine; `minimum`: the smallest that fits (minutes)."""

    def __init__(self, message: str, minimum: float):
        super().__init__(message)
        self.minimum = minimum


def plan_run(
    out: Path,
    key: dict[str, Any],
    budget_minutes: float,
    explicit: dict[str, int | None],
    explicit_prior_seconds: float | None,
    probe: Callable[[], float],
    prior_probe: Callable[[], float] | None = None,
    disc_probe: Callable[[], float] | None = None,
    shares: dict[str, float] | None = None,
    views: dict[str, int] | None = None,
    probe_wall_seconds: float | None = None,
    prior_trained: bool = True,
    view_pixels: int | None = None,
) -> Plan:
    """The run's plan: reused from `out/plan.json` when it was made for `key`, else made now (by
    calling `probe()` -> seconds per step unless every count is explicit) and written there.

    explicit: {stage: steps or None}; a number replaces the probe's figure for that stage.
    prior_probe: () -> seconds per scene-prior step on this machine, called when the GS probe runs
    (the prior's seconds become `prior_steps`); None where no prior is trained or its steps are fixed.
    disc_probe: () -> seconds TE-D's discriminator adds to an adversarial step, called likewise
    unless the adversarial count is explicit.
    views: {fixed stage: the views it works on} (`stage_costs.fixed_costs`; None: no fixed stage
    is estimated, the GS pool is the budget less the prior's share).
    probe_wall_seconds: the probes' wall time to count instead of the time measured here (a plan
    that takes another's rates takes its figure too, so the same budget gives the same counts).
    prior_trained: False where no stage will train the scene prior (CLG skipped, stage 1 filling
    without it): its steps are still planned (stage 1's key holds them) but cost no time.
    view_pixels: a working view's pixels, which the fixed stages' per-view seconds scale with
    (`stage_costs.fixed_costs`; None: the size they were measured at).
    Raises `BudgetTooSmall` (nothing written) when the GS pool left cannot give every budgeted GS
    stage `stage_costs.MIN_STEPS`."""
    path = Path(out) / PLAN_FILE
    have = read_plan(path) if path.exists() else None
    if have is not None and have.key == json.loads(json.dumps(key, default=str)):
        # Explicit counts win over the file's; `read_plan` has checked they agree, so a resumed run
        # trains exactly what the first one planned.
        steps = {k: int(explicit[k]) if explicit.get(k) is not None else n for k, n in have.steps.items()}
        plan = replace(have, steps=steps)
        log.info("plan reused from %s: %s", path, plan.describe())
        return plan
    secs = explicit_prior_seconds if explicit_prior_seconds is not None else prior_seconds(budget_minutes)
    if all(explicit.get(k) is not None for k in ("refgs", "ted_finetune", "ted_adversarial")):
        steps = {k: int(explicit[k]) for k in ("refgs", "ted_finetune", "ted_adversarial")}
        saved = json.loads(json.dumps(key, default=str))
        plan = Plan(steps, dict.fromkeys(steps), secs, None, "explicit", saved,
                    shares=None if shares is None else dict(shares))  # fmt: skip
        write_text(path, json.dumps(asdict(plan), indent=2, sort_keys=True))
        log.info("plan (explicit): %s; written to %s", plan.describe(), path)
        return plan
    log.info("timing probe: %d Scaffold-GS steps on this machine to turn %.0f minutes into steps",
             PROBE_STEPS + PROBE_WARMUP, budget_minutes)  # fmt: skip
    t0 = time.perf_counter()
    spp = float(probe())
    prior_spp = prior_steps = None
    if prior_probe is not None:
        from coin_cl.diffusion.scene_prior import steps_for_seconds

        prior_spp = float(prior_probe())
        prior_steps = steps_for_seconds(secs, prior_spp)
        if explicit_prior_seconds is None:
            # The measured minimum is a step count (PRIOR_MIN_SECONDS at the 2-core rate it was
            # measured at): a slower machine spends longer on it rather than train a noisier prior.
            prior_steps = max(prior_steps, steps_for_seconds(PRIOR_MIN_SECONDS))
    disc = None
    if disc_probe is not None and explicit.get("ted_adversarial") is None:
        disc = float(disc_probe())
        if not math.isfinite(disc) or disc < 0:
            raise ValueError(f"discriminator seconds per step must be a non-negative number, got {disc}")
    wall = time.perf_counter() - t0 if probe_wall_seconds is None else float(probe_wall_seconds)
    draft = Plan({}, {}, secs, spp, "probe", {}, prior_steps, prior_spp, disc, shares)
    trained = (prior_steps, prior_spp) if prior_trained else (None, None)
    if views is not None:
        fixed = costs.fixed_costs(views, costs.machine_factor(prior_spp), *trained, view_pixels=view_pixels)
    else:
        fixed = {"prior": secs} if prior_trained else {}
    given = {k: int(n) for k, n in explicit.items() if n is not None and k in gs_weights(shares)}
    given_s = sum(n * gs_step_seconds(draft, k, None) for k, n in given.items())
    pool = 60.0 * budget_minutes - wall - sum(fixed.values()) - given_s
    free = {k: w for k, w in gs_weights(shares).items() if k not in given}
    need = costs.minimum_pool(free, {k: gs_step_seconds(draft, k, None) for k in free})
    if pool < need or pool <= 0:
        raise too_small(budget_minutes, wall + given_s, fixed, need, draft, explicit_prior_seconds, free)
    per_step = {k: gs_step_seconds(draft, k, None) for k in free}
    split = costs.split_seconds(pool, free, costs.min_floors(free, per_step))
    auto = {k: int(split[k] / per_step[k]) for k in free}
    if "refgs" in auto:
        auto["refgs"] = max(1, auto["refgs"])
    steps = {k: given.get(k, auto.get(k, 0)) for k in gs_weights(shares)}
    minutes: dict[str, float | None] = {k: None if k in given else split[k] / 60.0 for k in steps}
    plan = Plan(
        steps=steps,
        minutes=minutes,
        prior_seconds=secs,
        probe_seconds_per_step=spp,
        source="probe",
        key=json.loads(json.dumps(key, default=str)),
        prior_steps=prior_steps,
        prior_seconds_per_step=prior_spp,
        disc_seconds_per_step=disc,
        shares=None if shares is None else dict(shares),
        fixed_seconds=fixed,
        probe_wall_seconds=wall,
    )
    write_text(path, json.dumps(asdict(plan), indent=2, sort_keys=True))
    log.info("plan (probe %.3f s/step%s%s; probes %.0f s, fixed stages ~%.1f min: %s): %s; written to %s",
             spp,
             "" if prior_spp is None else f", scene prior {prior_spp:.2f} s/step",
             "" if disc is None else f", discriminator {disc:.3f} s/step", wall, sum(fixed.values()) / 60,
             ", ".join(f"{k} {v:.0f} s" for k, v in fixed.items()), plan.describe(), path)  # fmt: skip
    return plan


def too_small(
    budget_minutes: float,
    fixed_gs: float,
    fixed: dict[str, float],
    need: float,
    plan: Plan,
    explicit_prior_seconds: float | None,
    free: dict[str, float],
) -> BudgetTooSmall:
    """The refusal of a budget that cannot fit: one line with the minimum budget that does
    (`stage_costs.minimum_budget`) and what it is made of. fixed_gs: the probes' and the explicit
    counts' seconds; fixed: the fixed stages' estimates; need: the GS pool MIN_STEPS take."""
    # The prior's cost in a budget B: its floor, or its share of B at PRIOR_STEP_COST per probed step.
    floor, share = fixed.get("prior", 0.0), 0.0
    trained = "prior" in fixed  # else no stage trains it: no floor, no share
    if trained and explicit_prior_seconds is None and plan.prior_seconds_per_step is not None:
        from coin_cl.diffusion.scene_prior import steps_for_seconds

        floor = steps_for_seconds(PRIOR_MIN_SECONDS) * plan.prior_seconds_per_step * costs.PRIOR_STEP_COST
        share = BUDGET_SHARES["prior"] * costs.PRIOR_STEP_COST
    elif trained and explicit_prior_seconds is None:  # no prior probe: its nominal seconds
        floor, share = PRIOR_MIN_SECONDS, BUDGET_SHARES["prior"]
    others = fixed_gs + sum(v for k, v in fixed.items() if k != "prior")
    least = math.ceil(10 * costs.minimum_budget(others, floor, share, need)) / 10
    mins = ", ".join(f"{k} {costs.MIN_STEPS[k]}" for k in free if costs.MIN_STEPS.get(k))
    return BudgetTooSmall(
        f"--budget {budget_minutes:g} minutes cannot fit this run on this machine: it needs at least "
        f"{least:g} minutes (probes and fixed stages ~{others / 60:.1f} min, "
        + (f"scene prior ~{floor / 60:.1f} min, " if trained else "")
        + f"the fewest useful GS steps ({mins}) ~{need / 60:.1f} min); give --budget {least:g} or more, "
        "or fixed step counts with --iters", least)  # fmt: skip


def gs_step_seconds(plan: Plan, stage: str, refgs_seconds_per_step: float | None) -> float:
    """Seconds one step of GS stage `stage` takes: TE-D's from Ref-GS's measured rate where it ran
    (`ted_step_seconds`), else from the probe's rate at the stage's STEP_COST (an adversarial step
    with the discriminator's measured cost where probed)."""
    if stage in ("ted_finetune", "ted_adversarial"):
        rate = refgs_seconds_per_step
        if rate is None:
            rate = plan.probe_seconds_per_step * STEP_COST["refgs"]
        return ted_step_seconds(plan, stage, rate)
    return plan.probe_seconds_per_step * STEP_COST[stage]


def ted_step_seconds(plan: Plan, phase: str, refgs_seconds_per_step: float) -> float:
    """Seconds a TE-D step of `phase` ("ted_finetune", "ted_adversarial") takes, from Ref-GS's
    measured seconds per step: a fine-tune step costs a fixed share of a Ref-GS step (the same
    renders and losses); an adversarial step that plus the discriminator's cost where the plan
    measured it (`Plan.disc_seconds_per_step`), else the fixed ratio `TED_PER_REFGS_STEP`."""
    finetune = refgs_seconds_per_step * TED_PER_REFGS_STEP["ted_finetune"]
    if phase == "ted_finetune":
        return finetune
    if plan.disc_seconds_per_step is not None:
        return finetune + plan.disc_seconds_per_step
    return refgs_seconds_per_step * TED_PER_REFGS_STEP[phase]
