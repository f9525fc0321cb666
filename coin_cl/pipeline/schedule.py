"""The schedule a run folder trains: each GS stage's step count planned again when the stage is
reached, from what the budget has left (`coin_cl.pipeline.budget`'s rule, item 4 of its doc).

What is left for a stage is the budget less the probes, less the seconds the finished stages'
manifests record, less the estimates of the fixed stages still to come; the GS stages from this one
on share it by their weights, each first getting its fewest useful steps. Every function here is a
pure function of `OUT/plan.json` and the manifests already written (it writes and logs nothing),
so a stage's key and the stage itself get the same numbers, and a killed run resumes to the same
schedule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from coin_cl.pipeline import stage_costs as costs
from coin_cl.pipeline.budget import (
    CAP_FACTOR,
    PLAN_FILE,
    Plan,
    gs_step_seconds,
    gs_weights,
    read_plan,
)
from coin_cl.schema import MAX_STEPS, SchemaError, run_folder_fix


def seconds_left(out: Path, plan: Plan, stage: str, budget_minutes: float) -> tuple[float, bool]:
    """(seconds the budget leaves for the budget-planned GS stages from `stage` on, whether any
    stage before it recorded its seconds). The budget's seconds less: the probes' wall time; each
    stage before `stage` (in `stage_costs.STAGE_ORDER`) by the seconds its manifest in `out`
    records, or by its estimate where it has none; the estimates of the fixed stages after it and
    of the explicit GS counts; the scene prior's training until a stage that trains it (1_inpaint
    where its result names a prior, else 3_clg) has recorded its seconds. Only the stages the plan
    has count (a fixed stage the run leaves out has no estimate). A pure function of the plan and
    the manifests (it writes and logs nothing)."""
    from coin_cl.pipeline.runner import read_manifest

    fixed = plan.fixed_seconds if plan.fixed_seconds is not None else {"prior": plan.prior_seconds}
    order = costs.STAGE_ORDER
    at = order.index(stage)
    gs_of = {s: [k for k in plan.steps if costs.GS_STAGES[k] == s] for s in order}

    def estimate(s: str) -> float:
        if s in fixed:
            return fixed[s]
        return sum(_planned_seconds(plan, k) for k in gs_of[s])

    left = 60.0 * budget_minutes - (plan.probe_wall_seconds or 0.0)
    measured = prior_spent = False
    for s in order[:at]:
        if s not in fixed and not gs_of[s]:
            continue
        man = read_manifest(Path(out) / s)
        if man is None:
            left -= estimate(s)
            continue
        left -= float(man["seconds"])
        measured = True
        prior_spent |= s == "3_clg" or (s == "1_inpaint" and bool(man["result"].get("prior")))
    for s in order[at + 1 :]:
        left -= fixed.get(s, 0.0)
        left -= sum(_planned_seconds(plan, k) for k in gs_of[s] if plan.minutes.get(k) is None)
    left -= sum(_planned_seconds(plan, k) for k in gs_of[stage] if plan.minutes.get(k) is None)
    if not prior_spent:
        left -= fixed.get("prior", 0.0)
    return left, measured


def _planned_seconds(plan: Plan, k: str) -> float:
    """The seconds the plan gives GS stage `k`: its minutes, or its explicit count at its cost."""
    m = plan.minutes.get(k)
    if m is not None:
        return 60.0 * m
    if plan.probe_seconds_per_step is None:
        return 0.0
    return plan.steps[k] * gs_step_seconds(plan, k, None)


@dataclass(frozen=True)
class Schedule:
    """A GS stage's schedule when it is reached. steps: {plan key: steps} of its GS stages
    ("refine"; "refgs"; "ted_finetune" and "ted_adversarial"); caps: the same keys -> seconds a
    budget-planned one may take (`CAP_FACTOR` x its planned time); refgs_seconds_per_step: Ref-GS's
    measured rate TE-D's counts were planned from (None: not run)."""

    steps: dict[str, int]
    caps: dict[str, float]
    refgs_seconds_per_step: float | None


def stage_schedule(out: Path, plan: Plan, stage: str, budget_minutes: float) -> Schedule:
    """The schedule of GS stage folder `stage` ("0_refine", "2_refgs", "4_ted") in run folder
    `out`: each budget-planned count planned again from what is left (`seconds_left`), shared with
    the budget-planned GS stages after it by their weights (`gs_weights`), at its cost per step
    (`gs_step_seconds`: TE-D's from the Ref-GS rate OUT/2_refgs/manifest.json records). Explicit
    counts are kept (no cap). Before any stage recorded its seconds: the plan's counts. A pure
    function of the plan and the manifests, so the stage's key and the stage itself get the same
    numbers, and a resumed run too."""
    mine = [k for k in plan.steps if costs.GS_STAGES[k] == stage]
    steps = {k: plan.steps[k] for k in mine}
    at = costs.STAGE_ORDER.index(stage)
    # Ref-GS's recorded rate only for the stages after it: when 0_refine or Ref-GS itself was
    # reached there was none, and a finished run's (or a resumed one's) 2_refgs manifest must not
    # change their counts, hence their keys, after the fact
    rate = refgs_step_seconds(out) if at > costs.STAGE_ORDER.index("2_refgs") else None
    left, measured = seconds_left(out, plan, stage, budget_minutes)
    weights = {k: w for k, w in gs_weights(plan.shares).items()
               if k in plan.steps and plan.minutes.get(k) is not None
               and costs.STAGE_ORDER.index(costs.GS_STAGES[k]) >= at}  # fmt: skip
    if not measured or plan.probe_seconds_per_step is None:
        caps = {k: plan.cap_seconds(k) for k in mine if k in weights}
        return Schedule(steps, caps, rate)
    rates = {k: gs_step_seconds(plan, k, rate) for k in weights}
    share = costs.split_seconds(left, weights, costs.min_floors(weights, rates))
    caps = {}
    for k in mine:
        if k not in weights:
            continue
        per_step = rates[k]
        # never past the schema's bound: a planted plan's tiny rate must not ask for 10^12 steps
        steps[k] = min(MAX_STEPS, int(share[k] / per_step))
        if k == "refgs":
            steps[k] = max(1, steps[k])
        caps[k] = CAP_FACTOR * max(steps[k], 1) * per_step
    return Schedule(steps, caps, rate)


def ted_schedule(out: Path, plan: Plan, budget_minutes: float) -> Schedule:
    """TE-D's schedule in run folder `out` (`stage_schedule` of 4_ted)."""
    return stage_schedule(out, plan, "4_ted", budget_minutes)


def refgs_schedule_span(plan: Plan, refgs_steps: int, ted_continues: bool) -> int:
    """The steps Ref-GS lays its learning-rate decay and anchor growth out over: its own, plus the
    plan's TE-D fine-tune steps where TE-D runs and continues that decay (`TEDConfig.rates`
    "continue"), so that the two stages train the model as one fit of their steps would. From the
    plan, not from TE-D's count planned again later: the stage's key must not change after Ref-GS
    ran."""
    if not ted_continues:
        return refgs_steps
    return refgs_steps + int(plan.steps.get("ted_finetune", 0))


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


def refgs_step_seconds(out: Path) -> float | None:
    """The seconds per Ref-GS step TE-D's steps are costed from (`budget.ted_step_seconds`): the
    late rate Ref-GS's manifest records (`result.late_seconds_per_step`, the last fifth of its run,
    the model at the size TE-D trains), else its mean over the run (a manifest without it); None
    when Ref-GS has not run."""
    from coin_cl.pipeline.runner import read_manifest

    n, seconds = refgs_rate(out)
    if not n:
        return None
    man = read_manifest(Path(out) / "2_refgs")
    late = None if man is None else man["result"].get("late_seconds_per_step")
    if late is None:
        return seconds / n
    if isinstance(late, bool) or not isinstance(late, int | float) or not (math.isfinite(late) and late > 0):
        path = Path(out) / "2_refgs" / "manifest.json"
        raise SchemaError(f"{path}: result.late_seconds_per_step {late!r} is not a positive number of "
                          f"seconds; {run_folder_fix(path, 'Ref-GS runs again')}")  # fmt: skip
    return float(late)


def run_steps(out: Path) -> dict[str, int]:
    """The step counts a run folder trains: its plan.json's, each GS stage's as re-planned when it
    was reached (`stage_schedule`, as during the run, from the manifests the folder holds); Ref-GS's
    as it planned it again from its first steps (its manifest's `result.iters`) once it has run."""
    from coin_cl.pipeline.runner import read_manifest

    path = Path(out) / PLAN_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: not a CoIn run folder (coin-cl run writes it)")
    plan = read_plan(path)
    steps = dict(plan.steps)
    for stage in ("0_refine", "2_refgs", "4_ted"):
        steps.update(stage_schedule(out, plan, stage, plan.key["budget_minutes"]).steps)
    man = read_manifest(Path(out) / "2_refgs")
    decided = None if man is None else man["result"].get("iters")
    if isinstance(decided, int) and not isinstance(decided, bool) and 1 <= decided <= MAX_STEPS:
        steps["refgs"] = decided
    return steps


def trained_steps(out: Path) -> dict[str, int]:
    """The GS steps a finished run folder really trained: 0_refine's fit, Ref-GS's and TE-D's phases
    as their manifests recorded them (a phase stopped at its time cap trained fewer than `run_steps` says),
    `run_steps`' count for a stage that recorded none (not run yet, or skipped: 0 then)."""
    out = Path(out)
    got = dict(run_steps(out))

    from coin_cl.pipeline.runner import read_manifest

    def result(stage: str) -> dict | None:
        man = read_manifest(out / stage)
        return None if man is None else man["result"]

    refine, refgs, ted = result("0_refine"), result("2_refgs"), result("4_ted")
    if "refine" in got and refine is not None and isinstance(refine.get("iters"), int):
        got["refine"] = int(refine["iters"])
    if refgs is not None and "steps" in refgs:
        got["refgs"] = int(refgs["steps"])
    for phase in ("finetune", "adversarial"):
        if ted is not None and isinstance(ted.get(phase), dict) and "step" in ted[phase]:
            got[f"ted_{phase}"] = int(ted[phase]["step"])
    return got
