"""The run's plan: working resolution and step counts from the minute budget (issue 20).

CoIn's published schedule (10k Ref-GS steps, 10k + 10k TE-D, paper supp. A) is far beyond 2 CPU
cores, so a run is planned from `--budget` minutes on the machine at hand:

1. Working resolution (`working_resolution`): the image scale 1/n (n an integer) that brings a
   view to at most `MAX_WORK_PIXELS` pixels. Measured on the shared SPIn-NeRF scene at budget 30
   (issue 20, docs/RESULTS.md): at 1008x567 the budget buys ~280 Ref-GS steps and the result loses
   to the naive baseline; at 504x284 (143k px) it buys ~700 and wins. `--resolution` overrides.
2. Step counts (`plan_steps`): a timing probe trains a plain Scaffold-GS on the scene's captured
   views at the working resolution for `PROBE_STEPS` steps (~10-30 s), which turns the budget's
   shares (`BUDGET_SHARES`) into steps with the measured cost of each GS stage relative to the
   probe's step (`STEP_COST`). The plan is written to `OUT/plan.json` and reused by every rerun of
   the same settings (so a rerun is the same run, and a killed run resumes to the same schedule);
   `--iters` / `CoInConfig.iters_*` replace the probe with fixed counts.
3. A safety cap: each GS stage also stops at `CAP_FACTOR` x its planned minutes (logged), so a
   machine much slower than its probe (another job starting) cannot run far over the budget.

TE-D's adversarial step is a fine-tune step plus its discriminator's cost, which a third probe
measures (~1 s; `ted.probe_discriminator_seconds`): that cost does not shrink with the images as a
GS step does, so a fixed ratio measured at 504x284 underplanned it 2.2x at 192x144.

The scene prior (CLG's denoiser) takes its share as seconds of training, never below
`PRIOR_MIN_SECONDS` (measured: below it, its fills are noise); its own probe (a few optimizer steps
of the prior, ~4 s) turns the seconds into steps on this machine, never fewer than the minimum's
steps at the rate it was measured at.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from coin_cl.atomic import write_text
from coin_cl.schema import MAX_STEPS, PLAN, SchemaError, parse, run_folder_fix
from coin_cl.timing import mean_step_seconds

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Scene

log = logging.getLogger(__name__)

# A view is brought to at most this many pixels by default (504x284 = 143k is the measured winner;
# see the module docstring). The scale is 1/n so that pixel grids stay aligned with the capture's.
MAX_WORK_PIXELS = 160_000
# Shares of the budget: the scene prior's training, Ref-GS, TE-D fine-tune, TE-D adversarial
# (CLG is counted in sampling steps, not minutes, and eval is extra).
BUDGET_SHARES = {"prior": 0.15, "refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.3}
# Mean seconds per step of each GS stage over a whole run, relative to the probe's plain Scaffold-GS
# step at the start of training (Ref-GS adds its terms and the model grows by densification; TE-D's
# adversarial phase renders patches for the discriminator). Ref-GS measured on SPIn-NeRF at 504x284
# (Zen 5, quiet machine; the default run of docs/RESULTS.md at 638718a): probe 0.236 s/step; Ref-GS
# 0.19-0.24 s/step over its first 100 steps (585k primitives), 0.7 s/step from step ~1000 (1.7M
# primitives, anchor attention on), 0.513 s/step on average over the 1535 steps its cap allowed of
# the 1668 planned at 1.6x: 2.2x the probe over a whole run. TE-D follows from it by
# TED_PER_REFGS_STEP and is planned again from Ref-GS's measured rate.
STEP_COST = {"refgs": 2.2, "ted_finetune": 2.2 * 69 / 84, "ted_adversarial": 2.2 * 69 / 68}
# A TE-D step's cost relative to a Ref-GS step, measured in full runs on SPIn-NeRF at 504x284 (69
# Ref-GS, 84 TE-D fine-tune, 68 TE-D adversarial steps per minute; docs/RESULTS.md, issue 12). TE-D's
# counts are planned again from Ref-GS's measured rate once it has run (`replan_ted`).
TED_PER_REFGS_STEP = {"ted_finetune": 69 / 84, "ted_adversarial": 69 / 68}
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
    """What each stage is given. steps: {"refgs", "ted_finetune", "ted_adversarial"} -> steps;
    minutes: the planned minutes of each (None where counts were given explicitly); prior_seconds:
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
    # phase gives its share to the fine-tune phase (`coin_plan.plan_for`).
    shares: dict[str, float] | None = None

    def cap_seconds(self, stage: str) -> float:
        """The safety cap of a GS stage (0: none, for explicit step counts)."""
        m = self.minutes.get(stage)
        return 0.0 if m is None else CAP_FACTOR * 60.0 * m

    def describe(self) -> str:
        parts = []
        for k, n in self.steps.items():
            m = self.minutes.get(k)
            parts.append(f"{k} {n} steps" + ("" if m is None else f" (~{m:.1f} min)"))
        prior = "" if self.prior_steps is None else f" ({self.prior_steps} steps)"
        return ", ".join(parts) + f", scene prior {self.prior_seconds:.0f} s{prior}"


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
    for i, k in enumerate(("refgs", "ted_finetune", "ted_adversarial")):
        n, minutes = plan.steps[k], plan.minutes[k]
        given = explicit[i] if isinstance(explicit, list) and len(explicit) == 4 else None
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
    budget_minutes: float, seconds_per_step: float, shares: dict[str, float] | None = None
) -> tuple[dict[str, int], dict[str, float]]:
    """({stage: steps}, {stage: minutes}) for a budget at a probe rate: each GS stage gets its share
    of the budget (`shares`, default BUDGET_SHARES) divided by its cost. Monotone: more budget or a
    faster machine never gives fewer steps. At least 1 Ref-GS step; TE-D may get 0 (then it passes
    Ref-GS through, logged)."""
    if not math.isfinite(seconds_per_step) or seconds_per_step <= 0:
        raise ValueError(f"probe seconds per step must be a positive number, got {seconds_per_step}")
    if not math.isfinite(budget_minutes) or budget_minutes <= 0:
        raise ValueError(f"budget must be a positive number of minutes, got {budget_minutes}")
    shares = shares or BUDGET_SHARES
    steps, minutes = {}, {}
    for k in ("refgs", "ted_finetune", "ted_adversarial"):
        minutes[k] = shares[k] * budget_minutes
        steps[k] = stage_steps(k, minutes[k], seconds_per_step)
    steps["refgs"] = max(1, steps["refgs"])
    return steps, minutes


def stage_steps(stage: str, minutes: float, seconds_per_step: float) -> int:
    """Steps of GS stage `stage` ("refgs", "ted_finetune", "ted_adversarial") in `minutes` at the
    probe's `seconds_per_step`: the stage's step costs STEP_COST[stage] probe steps."""
    return int(minutes * 60.0 / (seconds_per_step * STEP_COST[stage]))


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
) -> Plan:
    """The run's plan: reused from `out/plan.json` when it was made for `key`, else made now (by
    calling `probe()` -> seconds per step unless every count is explicit) and written there.

    explicit: {stage: steps or None}; a number replaces the probe's figure for that stage.
    prior_probe: () -> seconds per scene-prior step on this machine, called when the GS probe runs
    (the prior's seconds become `prior_steps`); None where no prior is trained or its steps are fixed.
    disc_probe: () -> seconds TE-D's discriminator adds to an adversarial step, called likewise
    unless the adversarial count is explicit."""
    path = Path(out) / PLAN_FILE
    have = read_plan(path) if path.exists() else None
    if have is not None and have.key == json.loads(json.dumps(key, default=str)):
        # Explicit counts win over the file's; `read_plan` has checked they agree, so a resumed run
        # trains exactly what the first one planned.
        steps = {k: int(explicit[k]) if explicit.get(k) is not None else n for k, n in have.steps.items()}
        plan = replace(have, steps=steps)
        log.info("plan reused from %s: %s", path, plan.describe())
        return plan
    spp = None
    if all(explicit.get(k) is not None for k in ("refgs", "ted_finetune", "ted_adversarial")):
        steps = {k: int(explicit[k]) for k in ("refgs", "ted_finetune", "ted_adversarial")}
        minutes: dict[str, float | None] = dict.fromkeys(steps)
        source = "explicit"
    else:
        log.info("timing probe: %d Scaffold-GS steps on this machine to turn %.0f minutes into steps",
                 PROBE_STEPS + PROBE_WARMUP, budget_minutes)  # fmt: skip
        spp = probe()
        auto, auto_min = steps_from_rate(budget_minutes, spp, shares)
        steps = {k: int(explicit[k]) if explicit.get(k) is not None else auto[k] for k in auto}
        minutes = {k: None if explicit.get(k) is not None else auto_min[k] for k in auto}
        source = "probe"
    secs = explicit_prior_seconds if explicit_prior_seconds is not None else prior_seconds(budget_minutes)
    prior_spp = prior_steps = None
    if source == "probe" and prior_probe is not None:
        from coin_cl.diffusion.scene_prior import steps_for_seconds

        prior_spp = float(prior_probe())
        prior_steps = steps_for_seconds(secs, prior_spp)
        if explicit_prior_seconds is None:
            # The measured minimum is a step count (PRIOR_MIN_SECONDS at the 2-core rate it was
            # measured at): a slower machine spends longer on it rather than train a noisier prior.
            prior_steps = max(prior_steps, steps_for_seconds(PRIOR_MIN_SECONDS))
    disc = None
    if source == "probe" and disc_probe is not None and explicit.get("ted_adversarial") is None:
        disc = float(disc_probe())
        if not math.isfinite(disc) or disc < 0:
            raise ValueError(f"discriminator seconds per step must be a non-negative number, got {disc}")
    plan = Plan(
        steps=steps,
        minutes=minutes,
        prior_seconds=secs,
        probe_seconds_per_step=spp,
        source=source,
        key=json.loads(json.dumps(key, default=str)),
        prior_steps=prior_steps,
        prior_seconds_per_step=prior_spp,
        disc_seconds_per_step=disc,
        shares=None if shares is None else dict(shares),
    )
    write_text(path, json.dumps(asdict(plan), indent=2, sort_keys=True))
    log.info("plan (%s%s%s%s): %s; written to %s", source,
             "" if spp is None else f", probe {spp:.3f} s/step",
             "" if prior_spp is None else f", scene prior {prior_spp:.2f} s/step",
             "" if disc is None else f", discriminator {disc:.3f} s/step",
             plan.describe(), path)  # fmt: skip
    return plan


def replan_ted(
    plan: Plan, refgs_steps: int, refgs_train_seconds: float, budget_minutes: float
) -> dict[str, int]:
    """TE-D's step counts once Ref-GS has run, from its measured seconds per step: TE-D gets its
    share of the budget plus what Ref-GS left unspent of its own (minus its overrun), split by the
    shares, each phase at its measured cost relative to a Ref-GS step (`TED_PER_REFGS_STEP`).
    Explicit counts in `plan` are kept. Deterministic in its inputs, which 2_refgs's manifest holds,
    so a rerun gets the same counts (`run_steps` reads them back from a run folder)."""
    out = {k: plan.steps[k] for k in ("ted_finetune", "ted_adversarial")}
    free = [k for k in out if plan.minutes.get(k) is not None]
    if not free or refgs_steps < 1 or not (refgs_train_seconds > 0):
        return out
    spp = refgs_train_seconds / refgs_steps
    planned_refgs = (
        60.0 * BUDGET_SHARES["refgs"] * budget_minutes if plan.minutes.get("refgs") is not None else 0.0
    )
    spare = planned_refgs - refgs_train_seconds if planned_refgs else 0.0
    shares = plan.shares or BUDGET_SHARES
    pool = sum(60.0 * shares[k] * budget_minutes for k in free) + spare
    total_share = sum(shares[k] for k in free)
    for k in free:
        seconds = max(0.0, pool * shares[k] / total_share) if total_share > 0 else 0.0
        out[k] = int(seconds / ted_step_seconds(plan, k, spp))
    return out


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


def refgs_rate(out: Path) -> tuple[int, float]:
    """(steps, training seconds) that Ref-GS recorded in OUT/2_refgs/manifest.json; (0, 0.0) when it
    has not run."""
    from coin_cl.pipeline.runner import read_manifest

    man = read_manifest(Path(out) / "2_refgs")
    if man is None:
        return 0, 0.0
    res = man["result"]
    steps, minutes = res.get("steps", 0), res.get("train_minutes", 0.0)
    if not (isinstance(steps, int) and 0 <= steps <= MAX_STEPS and isinstance(minutes, int | float)
            and math.isfinite(minutes) and minutes >= 0):  # fmt: skip
        path = Path(out) / "2_refgs" / "manifest.json"
        raise SchemaError(f"{path}: result.steps {steps!r} / result.train_minutes {minutes!r} are not a "
                          f"step count and minutes; {run_folder_fix(path, 'Ref-GS runs again')}")  # fmt: skip
    return int(steps), 60.0 * float(minutes)


def run_steps(out: Path) -> dict[str, int]:
    """The step counts a run folder trains: its plan.json's, TE-D's as re-planned from Ref-GS's
    measured rate (`ted_schedule`, as during the run)."""
    path = Path(out) / PLAN_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: not a CoIn run folder (coin-cl run writes it)")
    plan = read_plan(path)
    return {**plan.steps, **ted_schedule(out, plan, plan.key["budget_minutes"]).steps}


def trained_steps(out: Path) -> dict[str, int]:
    """The GS steps a finished run folder really trained: Ref-GS's and TE-D's phases as their
    manifests recorded them (a phase stopped at its time cap trained fewer than `run_steps` says),
    `run_steps`' count for a stage that recorded none (not run yet, or skipped: 0 then)."""
    out = Path(out)
    got = dict(run_steps(out))

    from coin_cl.pipeline.runner import read_manifest

    def result(stage: str) -> dict | None:
        man = read_manifest(out / stage)
        return None if man is None else man["result"]

    refgs, ted = result("2_refgs"), result("4_ted")
    if refgs is not None and "steps" in refgs:
        got["refgs"] = int(refgs["steps"])
    for phase in ("finetune", "adversarial"):
        if ted is not None and isinstance(ted.get(phase), dict) and "step" in ted[phase]:
            got[f"ted_{phase}"] = int(ted[phase]["step"])
    return got


@dataclass(frozen=True)
class TedSchedule:
    """TE-D's schedule once Ref-GS has run. steps: {"ted_finetune", "ted_adversarial"} -> steps;
    caps: the same keys -> seconds a phase may take (`CAP_FACTOR` x its planned time; only the
    phases planned from the budget, and only once Ref-GS recorded a rate); refgs_seconds_per_step:
    Ref-GS's measured rate the counts were planned from (None: not run, the plan's counts stand)."""

    steps: dict[str, int]
    caps: dict[str, float]
    refgs_seconds_per_step: float | None


def ted_schedule(out: Path, plan: Plan, budget_minutes: float) -> TedSchedule:
    """TE-D's schedule in run folder `out`: its counts planned again from the Ref-GS rate that
    OUT/2_refgs/manifest.json records (`replan_ted`) and the phases' time caps; explicit counts
    are kept. A pure function of the plan and that manifest (it writes and logs nothing), so TE-D's
    stage key and the stage itself get the same numbers, and a rerun too."""
    n, seconds = refgs_rate(out)
    steps = replan_ted(plan, n, seconds, budget_minutes)
    if not n:
        return TedSchedule(steps, {}, None)
    spp = seconds / n
    caps = {k: CAP_FACTOR * steps[k] * ted_step_seconds(plan, k, spp)
            for k in steps if plan.minutes.get(k) is not None}  # fmt: skip
    return TedSchedule(steps, caps, spp)
