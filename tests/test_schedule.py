"""The schedule a run folder trains (coin_cl.pipeline.schedule): each GS stage planned again when it
is reached from what the stages before it recorded; the counts read back from a run folder."""

import json

import pytest

from coin_cl.pipeline import budget as B
from coin_cl.pipeline import schedule as S

_VIEWS = {"0_scene": 40, "1_inpaint": 30, "3_clg": 30, "eval": 40}
_NONE = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
_REFINED = {**B.BUDGET_SHARES, "refine": B.REFINE_SHARE}


def _plan(out, budget, spp=0.2, prior=0.9):
    return B.plan_run(out, {"budget_minutes": budget, "spp": spp, "prior": prior}, budget, _NONE, None,
                      lambda: spp, lambda: prior, lambda: 0.05, shares=_REFINED, views=_VIEWS,
                      probe_wall_seconds=5.0)  # fmt: skip


def _manifest(result: dict) -> dict:
    """A stage manifest as the runner writes it (`coin_cl.schema.MANIFEST`), holding `result`."""
    return {"key": "k", "settings": {}, "outputs": {}, "result": result, "seconds": 1.0}


def _stage(out, stage: str, result: dict, seconds: float) -> None:
    """A finished stage's manifest in run folder `out` (as the runner writes it) recording `seconds`."""
    (out / stage).mkdir(parents=True, exist_ok=True)
    (out / stage / "manifest.json").write_text(json.dumps({**_manifest(result), "seconds": seconds}))


def test_ted_is_planned_again_from_what_the_stages_before_it_recorded(tmp_path):
    """TE-D's counts once Ref-GS has run: the budget less the prior and the seconds 2_refgs's
    manifest records, at Ref-GS's measured rate; a Ref-GS that overran leaves TE-D less, one that
    ran early leaves it more; an explicit count is kept."""
    steps, minutes = B.steps_from_rate(30 * 0.85, 0.25)
    plan = B.Plan(steps, minutes, 270.0, 0.25, "probe", {})
    planned_refgs = 60 * minutes["refgs"]
    got = {}
    for name, f in (("on_plan", 1.0), ("slow", 1.2), ("fast", 0.6)):
        _stage(tmp_path / name, "2_refgs", {"steps": steps["refgs"], "train_minutes": f * planned_refgs / 60},
               f * planned_refgs)  # fmt: skip
        got[name] = S.ted_schedule(tmp_path / name, plan, 30).steps
    for k in got["on_plan"]:
        assert got["fast"][k] > got["on_plan"][k] > got["slow"][k] > 0
        assert abs(got["on_plan"][k] - steps[k]) <= 1  # on plan: the probe's counts
    # the seconds TE-D is given: the budget less the prior and what Ref-GS took
    spp = 0.6 * planned_refgs / steps["refgs"]
    given = sum(got["fast"][k] * spp * B.TED_PER_REFGS_STEP[k] for k in got["fast"])
    assert given == pytest.approx(30 * 60 - 270 - 0.6 * planned_refgs, rel=0.01)
    explicit = B.Plan(
        {**steps, "ted_finetune": 5}, {**minutes, "ted_finetune": None}, 270.0, 0.25, "probe", {}
    )
    assert S.ted_schedule(tmp_path / "slow", explicit, 30).steps["ted_finetune"] == 5
    assert S.ted_schedule(tmp_path / "none", plan, 30).steps == {k: steps[k] for k in got["on_plan"]}


def test_run_steps_reads_back_what_a_run_trains(tmp_path):
    """A run folder's counts: plan.json's before Ref-GS ran, TE-D re-planned from 2_refgs's
    recorded rate after (the same numbers `ted_schedule` gives the run)."""
    key = {"budget_minutes": 30, "size": [64, 48]}
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    plan = B.plan_run(tmp_path, key, 30, none, None, lambda: 0.25)
    assert S.run_steps(tmp_path) == plan.steps
    slow = 1.5 * 60 * plan.minutes["refgs"]  # Ref-GS overran: TE-D gets fewer steps
    _stage(tmp_path, "2_refgs", {"steps": plan.steps["refgs"], "train_minutes": slow / 60}, slow)
    got = S.run_steps(tmp_path)
    assert got == {**plan.steps, **S.ted_schedule(tmp_path, plan, 30).steps}
    assert got["ted_finetune"] < plan.steps["ted_finetune"] and got["refgs"] == plan.steps["refgs"]
    # Ref-GS planned its count again from its first steps: the count it decided is the run's
    decided = plan.steps["refgs"] + 17
    _stage(tmp_path, "2_refgs", {"iters": decided, "steps": decided, "train_minutes": slow / 60}, slow)
    ted = S.ted_schedule(tmp_path, plan, 30).steps
    assert S.run_steps(tmp_path) == {**plan.steps, **ted, "refgs": decided}
    with pytest.raises(FileNotFoundError, match="plan.json"):
        S.run_steps(tmp_path / "nothing")


def test_ted_schedule_is_a_pure_function_of_the_plan_and_refgs_manifest(tmp_path):
    """TE-D's schedule (its stage key and the stage itself both compute it): the re-planned counts of
    `replan_ted` with each budget-planned phase's cap, the same numbers on every call, and nothing
    written or changed (the plan, its file, the manifest). Before Ref-GS ran: the plan's counts, no caps."""
    import copy

    key = {"budget_minutes": 30, "size": [64, 48]}
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    plan = B.plan_run(tmp_path, key, 30, none, None, lambda: 0.25)
    before = S.ted_schedule(tmp_path, plan, 30)
    ted = ("ted_finetune", "ted_adversarial")
    assert before == S.Schedule({k: plan.steps[k] for k in ted}, {k: plan.cap_seconds(k) for k in ted}, None)
    slow = 1.5 * 60 * plan.minutes["refgs"]
    _stage(tmp_path, "2_refgs", {"steps": plan.steps["refgs"], "train_minutes": slow / 60}, slow)
    files = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    kept = copy.deepcopy(plan)
    first, second = S.ted_schedule(tmp_path, plan, 30), S.ted_schedule(tmp_path, plan, 30)
    assert first == second and all(first.steps[k] < plan.steps[k] for k in ted)  # Ref-GS overran
    spp = slow / plan.steps["refgs"]
    assert first.refgs_seconds_per_step == pytest.approx(spp)
    for k, n in first.steps.items():
        assert n > 0 and first.caps[k] == pytest.approx(B.CAP_FACTOR * n * B.ted_step_seconds(plan, k, spp))
    assert plan == kept and {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == files
    # an explicit phase keeps its count and gets no cap
    fixed = B.Plan({**plan.steps, "ted_finetune": 5}, {**plan.minutes, "ted_finetune": None}, 270.0, 0.25,
                   "probe", {})  # fmt: skip
    sched = S.ted_schedule(tmp_path, fixed, 30)
    assert sched.steps["ted_finetune"] == 5 and set(sched.caps) == {"ted_adversarial"}


def test_trained_steps_count_what_stopped_at_a_cap(tmp_path):
    """The baselines' budget (`demo.baseline_steps`) is what CoIn trained: a TE-D phase stopped at
    its time cap recorded fewer steps than `run_steps` plans, and that count is taken; a stage
    with no manifest keeps the planned count."""
    key = {"budget_minutes": 30, "size": [64, 48]}
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    plan = B.plan_run(tmp_path, key, 30, none, None, lambda: 0.25)
    assert S.trained_steps(tmp_path) == S.run_steps(tmp_path) == plan.steps
    planned = 60 * plan.minutes["refgs"]
    for stage, result in (("2_refgs", {"steps": plan.steps["refgs"], "train_minutes": planned / 60}),
                          ("4_ted", {"finetune": {"step": 7}, "adversarial": {"step": 5}})):  # fmt: skip
        (tmp_path / stage).mkdir()
        (tmp_path / stage / "manifest.json").write_text(json.dumps(_manifest(result)))
    got = S.trained_steps(tmp_path)
    assert got == {"refgs": plan.steps["refgs"], "ted_finetune": 7, "ted_adversarial": 5}
    assert S.run_steps(tmp_path)["ted_adversarial"] > 5  # the plan still says what was planned


def _finish(out, stage: str, seconds: float, result: dict | None = None) -> None:
    _stage(out, stage, result or {}, seconds)


def test_each_gs_stage_is_planned_again_from_what_the_stages_before_recorded(tmp_path):
    """After each stage: the later GS stages share what is left (the budget less the recorded seconds
    and the estimates still to come). Stages on their estimate: the plan's counts; a stage that
    overran: every later GS stage gets less; one that ran early: more. The same files give the
    same counts (a resumed run trains what the first one planned)."""
    plan = _plan(tmp_path / "ref", 20)
    est = plan.fixed_seconds
    counts = {}
    for name, f in (("on", 1.0), ("over", 3.0), ("early", 0.5)):
        out = tmp_path / name
        out.mkdir()
        (out / B.PLAN_FILE).write_bytes((tmp_path / "ref" / B.PLAN_FILE).read_bytes())
        _finish(out, "0_scene", est["0_scene"])
        _finish(out, "0_refine", 60 * plan.minutes["refine"], {"iters": plan.steps["refine"]})
        _finish(out, "1_inpaint", f * est["1_inpaint"])  # the fixed stage that overran (or not)
        refgs = S.stage_schedule(out, plan, "2_refgs", 20)
        spent = refgs.steps["refgs"] * 0.2 * B.STEP_COST["refgs"]  # Ref-GS at its planned rate
        _finish(out, "2_refgs", spent, {"steps": refgs.steps["refgs"], "train_minutes": spent / 60})
        _finish(out, "3_clg", est["3_clg"] + est["prior"])
        counts[name] = S.run_steps(out)
        assert S.run_steps(out) == counts[name]  # the same files: the same counts
    for k in ("refgs", "ted_finetune", "ted_adversarial"):
        assert abs(counts["on"][k] - plan.steps[k]) <= 1, k  # on estimate: as planned
        assert counts["over"][k] < counts["on"][k] < counts["early"][k], k
    # the re-plan spends the budget: what TE-D is given plus what ran is the budget less eval's estimate
    out = tmp_path / "over"
    sched = S.ted_schedule(out, plan, 20)
    ted = sum(sched.steps[k] * B.gs_step_seconds(plan, k, sched.refgs_seconds_per_step) for k in sched.steps)
    ran = sum(json.loads((p / "manifest.json").read_text())["seconds"] for p in out.iterdir() if p.is_dir())
    assert ted + ran + est["eval"] + plan.probe_wall_seconds == pytest.approx(20 * 60, abs=5)


def test_ted_is_costed_from_refgs_late_rate_where_recorded(tmp_path):
    """TE-D trains the model at its final size: its steps are costed from the late Ref-GS rate the
    manifest records, from the mean where a manifest has none; a planted bad value is one line."""
    from coin_cl.schema import SchemaError

    assert S.refgs_step_seconds(tmp_path) is None  # Ref-GS not run
    _stage(tmp_path, "2_refgs", {"steps": 100, "train_minutes": 10 / 60}, 12.0)
    assert S.refgs_step_seconds(tmp_path) == pytest.approx(0.1)  # the mean: 10 s over 100 steps
    _stage(tmp_path, "2_refgs", {"steps": 100, "train_minutes": 10 / 60, "late_seconds_per_step": 0.18}, 12.0)
    assert S.refgs_step_seconds(tmp_path) == 0.18
    plan = _plan(tmp_path, 10.0)
    assert S.ted_schedule(tmp_path, plan, 10.0).refgs_seconds_per_step == 0.18
    for bad in (-1.0, "fast", float("inf")):
        _stage(tmp_path, "2_refgs", {"steps": 100, "train_minutes": 1.0, "late_seconds_per_step": bad}, 12.0)
        with pytest.raises(SchemaError, match="late_seconds_per_step"):
            S.refgs_step_seconds(tmp_path)


def test_a_stage_is_planned_from_the_stages_before_it_only(tmp_path):
    """A finished (or resumed) run folder plans 0_refine and Ref-GS as they were planned when they
    were reached: the manifests of later stages (Ref-GS's measured rate above all, which costs
    TE-D's share) do not move their counts, so their keys hold and a resumed run does not redo them."""
    plan = _plan(tmp_path, 10)
    _finish(tmp_path, "0_scene", plan.fixed_seconds["0_scene"])
    refine = S.stage_schedule(tmp_path, plan, "0_refine", 10).steps
    _finish(tmp_path, "0_refine", 30.0, {"iters": refine["refine"]})
    _finish(tmp_path, "1_inpaint", plan.fixed_seconds["1_inpaint"])
    refgs = S.stage_schedule(tmp_path, plan, "2_refgs", 10).steps
    # Ref-GS ran 3x slower than the probe said: TE-D is costed from that rate from now on
    spent = refgs["refgs"] * 3 * 0.2 * B.STEP_COST["refgs"]
    _finish(tmp_path, "2_refgs", spent, {"steps": refgs["refgs"], "train_minutes": spent / 60,
                                         "late_seconds_per_step": spent / refgs["refgs"]})  # fmt: skip
    _finish(tmp_path, "3_clg", plan.fixed_seconds["3_clg"] + plan.fixed_seconds["prior"])
    assert S.stage_schedule(tmp_path, plan, "0_refine", 10).steps == refine
    assert S.stage_schedule(tmp_path, plan, "2_refgs", 10).steps == refgs
    assert S.ted_schedule(tmp_path, plan, 10).refgs_seconds_per_step == pytest.approx(spent / refgs["refgs"])


def test_refgs_lays_its_schedules_over_the_te_d_fine_tune_it_continues_into():
    steps = {"refgs": 300, "ted_finetune": 500, "ted_adversarial": 0}
    plan = B.Plan(steps, dict.fromkeys(steps, 1.0), 0.0, 0.25, "probe", {})
    assert S.refgs_schedule_span(plan, 320, True) == 820  # Ref-GS's own count + the plan's TE-D's
    assert S.refgs_schedule_span(plan, 320, False) == 320  # TE-D restarts, or does not run
    no_ted = B.Plan({"refgs": 300}, {"refgs": 1.0}, 0.0, 0.25, "probe", {})
    assert S.refgs_schedule_span(no_ted, 300, True) == 300
