"""The run's plan (coin_cl.pipeline.budget): working resolution, steps from the probe's rate, the plan
recorded in OUT/plan.json and reused."""

import doctest
import itertools
import json
import math

import pytest

from coin_cl.pipeline import budget as B
from coin_cl.pipeline import schedule as S
from coin_cl.pipeline import stage_costs as costs


def test_working_resolution_brings_views_under_the_pixel_cap():
    assert B.working_resolution(1008, 567) == 0.5  # the shared scene: 504x284, the measured winner
    assert B.working_resolution(504, 284) == 1.0
    assert B.working_resolution(192, 144) == 1.0  # the demo room is left as it is
    for w, h in ((4032, 3024), (1920, 1080), (640, 480), (3000, 200), (100, 100000)):
        s = B.working_resolution(w, h)
        assert round(w * s) * round(h * s) <= B.MAX_WORK_PIXELS * 1.02, (w, h, s)
        n = round(1 / s)
        assert math.isclose(s, 1 / n)  # 1/n: pixel grids stay aligned with the capture's
        if n > 1:  # and the next larger scale would not fit
            assert w * h / (n - 1) ** 2 > B.MAX_WORK_PIXELS
    with pytest.raises(ValueError, match="0x10"):
        B.working_resolution(0, 10)


def test_working_resolution_is_monotone_in_pixels():
    sizes = [(w, round(w * 0.5625)) for w in range(200, 6000, 97)]
    work = [round(w * B.working_resolution(w, h)) for w, h in sizes]
    scales = [B.working_resolution(w, h) for w, h in sizes]
    assert all(a >= b for a, b in zip(scales, scales[1:]))  # larger captures are never scaled up
    assert max(work) <= 600


def test_the_docstring_examples_hold():
    assert doctest.testmod(B).failed == 0


def test_steps_grow_with_budget_and_machine_speed():
    prev = None
    for minutes in (1, 4, 10, 30, 60, 240):
        steps, planned = B.steps_from_rate(minutes, 0.2)
        assert steps["refgs"] >= 1
        assert sum(planned.values()) == pytest.approx(minutes)  # the GS pool is split whole
        if prev is not None:
            assert all(steps[k] >= prev[k] for k in steps)
        prev = steps
    slow, _ = B.steps_from_rate(30, 0.4)
    fast, _ = B.steps_from_rate(30, 0.1)
    assert all(fast[k] >= slow[k] for k in fast) and fast["refgs"] > slow["refgs"]
    # the plan spends each share: steps x cost x seconds per step = the share's minutes
    s, m = B.steps_from_rate(30, 0.25)
    for k in s:
        assert s[k] * B.STEP_COST[k] * 0.25 == pytest.approx(60 * m[k], abs=B.STEP_COST[k] * 0.25)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_rates_and_budgets_are_clear_errors(bad):
    with pytest.raises(ValueError, match="seconds per step"):
        B.steps_from_rate(30, bad)
    with pytest.raises(ValueError, match="budget"):
        B.steps_from_rate(bad, 0.2)


def test_plan_is_written_and_reused_for_the_same_key(tmp_path):
    calls = []

    def probe():
        calls.append(1)
        return 0.3

    key = {"budget_minutes": 10, "size": [64, 48]}
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    p1 = B.plan_run(tmp_path, key, 10, none, None, probe)
    assert calls == [1] and p1.source == "probe" and p1.probe_seconds_per_step == 0.3
    assert json.loads((tmp_path / B.PLAN_FILE).read_text())["steps"] == p1.steps
    p2 = B.plan_run(tmp_path, key, 10, none, None, probe)
    assert calls == [1] and p2 == p1  # reused: a rerun is the same run
    p3 = B.plan_run(tmp_path, {**key, "budget_minutes": 20}, 20, none, None, probe)
    assert calls == [1, 1] and p3.steps["refgs"] > p1.steps["refgs"]
    assert p3.cap_seconds("refgs") == pytest.approx(B.CAP_FACTOR * 60 * p3.minutes["refgs"])


def test_explicit_counts_need_no_probe_and_have_no_cap(tmp_path):
    def probe():
        raise AssertionError("no probe for explicit counts")

    p = B.plan_run(tmp_path, {"k": 1}, 30, {"refgs": 7, "ted_finetune": 2, "ted_adversarial": 0}, 5.0, probe)
    assert p.steps == {"refgs": 7, "ted_finetune": 2, "ted_adversarial": 0}
    assert p.source == "explicit" and p.prior_seconds == 5.0 and p.cap_seconds("refgs") == 0.0
    # one explicit count: the probe plans the others, the given one is kept
    q = B.plan_run(tmp_path / "b", {"k": 2}, 30, {"refgs": 7, "ted_finetune": None, "ted_adversarial": None},
                   None, lambda: 0.5)  # fmt: skip
    assert q.steps["refgs"] == 7 and q.minutes["refgs"] is None and q.steps["ted_finetune"] > 0


def test_scene_prior_steps_follow_its_own_probe(tmp_path):
    """The prior's seconds become steps at the rate measured here: a machine twice as slow trains
    half the steps (the fixed 2-core rate had a slower machine run 1.5x over its share)."""
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    fast = B.plan_run(tmp_path / "a", {"k": 1}, 10, none, 120.0, lambda: 0.2, lambda: 0.9)
    slow = B.plan_run(tmp_path / "b", {"k": 1}, 10, none, 120.0, lambda: 0.2, lambda: 1.8)
    assert (fast.prior_steps, slow.prior_steps) == (133, 67)  # explicit seconds: as asked
    # from the budget (60 min: 540 s): steps at the measured rate, never under the minimum's steps
    big = B.plan_run(tmp_path / "e", {"k": 1}, 60, none, None, lambda: 0.2, lambda: 1.8)
    small = B.plan_run(tmp_path / "f", {"k": 1}, 3, none, None, lambda: 0.05, lambda: 1.8)
    assert big.prior_seconds == 540 and big.prior_steps == 300
    assert small.prior_seconds == B.PRIOR_MIN_SECONDS and small.prior_steps == 133
    assert fast.prior_seconds_per_step == 0.9 and "(133 steps)" in fast.describe()
    # a run that trains no prior plans its steps (stage 1's key holds them) but does not claim the time
    untrained = B.plan_run(tmp_path / "g", {"k": 1}, 10, none, 120.0, lambda: 0.2, lambda: 0.9,
                           prior_trained=False)  # fmt: skip
    assert untrained.prior_steps == 133 and "no scene prior trained" in untrained.describe()
    assert "scene prior 120 s" in fast.describe()
    assert B.plan_run(tmp_path / "a", {"k": 1}, 10, none, 120.0, lambda: 0.2, lambda: 5.0) == fast  # reused

    def never():
        raise AssertionError("no prior probe for explicit counts")

    counts = {"refgs": 7, "ted_finetune": 2, "ted_adversarial": 0}
    p = B.plan_run(tmp_path / "c", {"k": 2}, 10, counts, 120.0, never, never)
    assert p.prior_steps is None  # explicit: the fixed rate, the same prior on any machine
    with pytest.raises(ValueError, match="scene prior seconds per step"):
        B.plan_run(tmp_path / "d", {"k": 3}, 10, none, 120.0, lambda: 0.2, lambda: float("nan"))
    # a plan written before the prior had its probe reads back without one
    old = json.loads((tmp_path / "a" / B.PLAN_FILE).read_text())
    del old["prior_steps"], old["prior_seconds_per_step"]
    (tmp_path / "a" / B.PLAN_FILE).write_text(json.dumps(old))
    assert B.plan_run(tmp_path / "a", {"k": 1}, 10, none, 120.0, lambda: 0.2, never).prior_steps is None


def test_adversarial_steps_add_the_discriminators_measured_cost(tmp_path):
    """With the discriminator's cost measured, an adversarial step is a fine-tune step plus it: on
    small images (a cheap GS step) that is several fine-tune steps, as the 192x144 room measured."""
    steps, minutes = B.steps_from_rate(3, 0.1)
    ratio = B.Plan(steps, minutes, 120.0, 0.1, "probe", {})
    measured = B.Plan(steps, minutes, 120.0, 0.1, "probe", {}, disc_seconds_per_step=0.5)
    spp = 0.16  # Ref-GS's measured seconds per step
    assert B.ted_step_seconds(measured, "ted_adversarial", spp) == pytest.approx(
        spp * B.TED_PER_REFGS_STEP["ted_finetune"] + 0.5
    )
    assert B.ted_step_seconds(ratio, "ted_adversarial", spp) == pytest.approx(
        spp * B.TED_PER_REFGS_STEP["ted_adversarial"]
    )
    for plan in (ratio, measured):
        assert B.ted_step_seconds(plan, "ted_finetune", spp) == pytest.approx(
            spp * B.TED_PER_REFGS_STEP["ted_finetune"]
        )
    _stage(tmp_path, "2_refgs", {"steps": 300, "train_minutes": 300 * spp / 60}, 300 * spp)
    a, b = (S.ted_schedule(tmp_path, p, 3).steps for p in (ratio, measured))
    assert a["ted_finetune"] == b["ted_finetune"] and b["ted_adversarial"] < a["ted_adversarial"] / 2
    # the plan measures it when the GS probe runs, unless the adversarial count is given
    calls = []
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    p1 = B.plan_run(
        tmp_path / "a", {"k": 1}, 3, none, None, lambda: 0.1, None, lambda: calls.append(1) or 0.25
    )
    assert calls == [1] and p1.disc_seconds_per_step == 0.25
    p2 = B.plan_run(tmp_path / "b", {"k": 1}, 3, {**none, "ted_adversarial": 5}, None, lambda: 0.1, None,
                    lambda: calls.append(1) or 0.25)  # fmt: skip
    assert calls == [1] and p2.disc_seconds_per_step is None
    with pytest.raises(ValueError, match="discriminator seconds per step"):
        B.plan_run(tmp_path / "c", {"k": 1}, 3, none, None, lambda: 0.1, None, lambda: float("nan"))


def test_probe_measures_a_positive_rate_on_a_tiny_scene(tmp_path):
    from coin_cl.scene import load_scene, write_synthetic

    scene = load_scene(write_synthetic(tmp_path / "room", n_views=4, width=48, height=32, seed=0))
    spp = B.probe_seconds_per_step(scene, list(scene.train_idx))
    assert math.isfinite(spp) and 0 < spp < 10


def _stage(out, stage: str, result: dict, seconds: float) -> None:
    """A finished stage's manifest in run folder `out` (as the runner writes it) recording `seconds`."""
    (out / stage).mkdir(parents=True, exist_ok=True)
    (out / stage / "manifest.json").write_text(json.dumps({**_manifest(result), "seconds": seconds}))


def _manifest(result: dict) -> dict:
    """A stage manifest as the runner writes it (`coin_cl.schema.MANIFEST`), holding `result`."""
    return {"key": "k", "settings": {}, "outputs": {}, "result": result, "seconds": 1.0}


def test_standalone_steps_use_the_pipelines_rule():
    """One minute->steps rule: a stage run on its own (`run_refgs(budget_minutes=...)`) gets the
    steps `steps_from_rate` gives that stage for the same minutes at the same probe rate."""
    from coin_cl.gs.model_kinds import REFERENCE_ITERS

    def probe():
        raise AssertionError("no probe needed")

    assert B.standalone_steps("refgs", None, None, probe) == REFERENCE_ITERS
    assert B.standalone_steps("refgs", 10.0, 123, probe) == 123
    steps, minutes = B.steps_from_rate(8.0, 0.3)
    for k in steps:
        assert B.standalone_steps(k, minutes[k], None, lambda: 0.3) == steps[k] > 0
    assert B.standalone_steps("refgs", 2.0, None, lambda: 0.5) == int(120 / (0.5 * B.STEP_COST["refgs"]))
    assert B.standalone_steps("refgs", 1e-4, None, lambda: 0.5) == 1  # at least one step
    with pytest.raises(ValueError, match="budget_minutes"):
        B.standalone_steps("refgs", 0.0, None, probe)
    with pytest.raises(ValueError, match="iters"):
        B.standalone_steps("refgs", None, 0, probe)
    with pytest.raises(ValueError, match="probe"):
        B.standalone_steps("refgs", 1.0, None, lambda: float("nan"))


def test_refgs_count_from_its_first_steps_prices_the_growth_its_cap_allows():
    """Ref-GS's re-plan (`refgs_steps_from_rate`): a model at or over its size cap costs its first
    steps' rate throughout; one that may grow k-fold costs k^GROWTH_COST_EXPONENT of it on average
    (it grows early). More seconds or a faster step never give fewer steps; the floor is the plan's
    minimum; bad rates are errors."""
    steps, mean = B.refgs_steps_from_rate(60.0, 0.2, 553_000, 97_000)
    assert mean == 0.2 and steps == 300
    steps, mean = B.refgs_steps_from_rate(60.0, 0.2, 50_000, 200_000)
    assert mean == pytest.approx(0.2 * 4**B.GROWTH_COST_EXPONENT) and steps == int(60.0 / mean)
    assert B.refgs_steps_from_rate(60.0, 0.2, 50_000, 0) == (300, 0.2)  # no cap known: no growth priced
    assert B.refgs_steps_from_rate(1.0, 0.2, 1, 1)[0] == costs.MIN_STEPS["refgs"]
    grid = [(s, r) for s in (10.0, 60.0, 600.0) for r in (0.05, 0.2, 1.0)]
    for (s1, r1), (s2, r2) in itertools.product(grid, grid):
        if s1 <= s2 and r1 >= r2:
            assert (
                B.refgs_steps_from_rate(s1, r1, 1000, 3000)[0]
                <= B.refgs_steps_from_rate(s2, r2, 1000, 3000)[0]
            )
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="seconds per step"):
            B.refgs_steps_from_rate(60.0, bad, 1000, 3000)
    with pytest.raises(ValueError, match="seconds"):
        B.refgs_steps_from_rate(float("nan"), 0.2, 1000, 3000)


def test_run_ted_refuses_counts_left_to_a_plan(tmp_path):
    from coin_cl.pipeline.ted import TEDConfig, run_ted

    with pytest.raises(ValueError, match="TEDConfig.iters_finetune is None"):
        run_ted(None, [], [], tmp_path, TEDConfig(iters_adversarial=0))


def _planted(tmp_path, key, **change):
    """A plan made by plan_run for `key`, with the fields in `change` replaced (a planted file)."""
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    B.plan_run(tmp_path, key, 30, none, None, lambda: 0.25)
    doc = json.loads((tmp_path / "plan.json").read_text())
    for k, v in change.items():
        doc[k] = v if not isinstance(v, dict) else {**doc[k], **v}
    (tmp_path / "plan.json").write_text(json.dumps(doc))
    return doc


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"steps": {"refgs": 10**9}}, "steps.refgs is 1000000000"),
        ({"steps": {"refgs": 10**6}}, "steps.refgs is 1000000, more than"),
        ({"prior_steps": 10**8}, "prior_steps is 100000000"),
        ({"source": "oracle"}, "source is"),
        ({"extra": 1}, "unknown key extra"),
    ],
)
def test_a_plan_no_run_could_have_made_is_refused(tmp_path, change, field):
    """A plan.json asking for steps beyond what its own budget and rate give (or malformed) is an
    error naming the file and the field, not a schedule that is obeyed."""
    key = {"budget_minutes": 30, "size": [64, 48]}
    _planted(tmp_path, key, **change)
    none = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
    for read in (
        lambda: B.plan_run(tmp_path, key, 30, none, None, lambda: 0.25),
        lambda: S.run_steps(tmp_path),
    ):
        with pytest.raises(ValueError) as e:
            read()
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(str(tmp_path / "plan.json")) and field in msg
        assert "delete" in msg


def test_explicit_counts_win_over_a_planted_plan(tmp_path):
    """With explicit counts (--iters) a recorded plan of the same key that disagrees is refused; one
    that agrees is reused unchanged (a resumed run trains what the first planned)."""
    key = {"budget_minutes": 30, "explicit": [3, 3, 3, None]}
    counts = {"refgs": 3, "ted_finetune": 3, "ted_adversarial": 3}
    first = B.plan_run(tmp_path, key, 30, counts, None, lambda: 0.25)
    assert B.plan_run(tmp_path, key, 30, counts, None, lambda: 0.25) == first
    doc = json.loads((tmp_path / "plan.json").read_text())
    doc["steps"]["refgs"] = 10**6
    (tmp_path / "plan.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="steps.refgs is 1000000 but key.explicit gives 3"):
        B.plan_run(tmp_path, key, 30, counts, None, lambda: 0.25)


# The whole-run rule: the budget holds every stage (module doc, `stage_costs`).
_VIEWS = {"0_scene": 40, "1_inpaint": 30, "3_clg": 30, "eval": 40}
_NONE = dict.fromkeys(("refgs", "ted_finetune", "ted_adversarial"))
_REFINED = {**B.BUDGET_SHARES, "refine": B.REFINE_SHARE}


def _plan(out, budget, spp=0.2, prior=0.9, views=_VIEWS, shares=_REFINED, wall=5.0, pixels=None):
    return B.plan_run(out, {"budget_minutes": budget, "spp": spp, "prior": prior}, budget, _NONE, None,
                      lambda: spp, lambda: prior, lambda: 0.05, shares=shares, views=views,
                      probe_wall_seconds=wall, view_pixels=pixels)  # fmt: skip


def test_the_budget_holds_every_stage_fixed_costs_off_then_gs_steps(tmp_path):
    """Stage costs in, steps out: the GS pool is the budget less the probes, the fixed stages and the
    prior; each GS stage's steps x its cost (growth included: STEP_COST) spend its share of it; more
    views (dearer fixed stages) leave fewer GS steps; every stage has its own count (0_refine's fit too)."""
    plan = _plan(tmp_path / "a", 20)
    fixed = sum(plan.fixed_seconds.values())
    assert set(plan.fixed_seconds) == {*_VIEWS, "prior"} and plan.probe_wall_seconds == 5.0
    pool = 20 * 60 - 5.0 - fixed
    assert sum(60 * m for m in plan.minutes.values()) == pytest.approx(pool)
    for k in ("refine", "refgs", "ted_finetune"):
        step = 0.2 * B.STEP_COST[k]
        assert plan.steps[k] * step == pytest.approx(60 * plan.minutes[k], abs=step)
    adv = B.gs_step_seconds(plan, "ted_adversarial", None)  # the discriminator's measured cost in it
    assert plan.steps["ted_adversarial"] * adv == pytest.approx(60 * plan.minutes["ted_adversarial"], abs=adv)
    crowded = _plan(tmp_path / "b", 20, views={k: 4 * n for k, n in _VIEWS.items()})
    assert all(crowded.steps[k] < plan.steps[k] for k in plan.steps)
    plain = _plan(tmp_path / "c", 20, shares=None)  # a run without the split: no refine share
    assert "refine" not in plain.steps and plain.steps["refgs"] > plan.steps["refgs"]
    # larger views: the fixed stages' per-view work grows with their pixels, the GS pool shrinks
    big = _plan(tmp_path / "d", 20, pixels=4 * costs.REFERENCE_PIXELS)
    assert big.fixed_seconds["1_inpaint"] > 3 * plan.fixed_seconds["1_inpaint"] - 3 * 5.0
    assert big.fixed_seconds["prior"] == plan.fixed_seconds["prior"]
    assert all(big.steps[k] < plan.steps[k] for k in plan.steps)


def test_steps_are_monotone_in_budget_and_machine_speed(tmp_path):
    prev = None
    for budget in (10, 15, 20, 30, 60, 120):
        plan = _plan(tmp_path / f"b{budget}", budget)
        if prev is not None:
            assert all(plan.steps[k] >= prev.steps[k] for k in plan.steps), budget
        prev = plan
    fast, slow = (
        _plan(tmp_path / "fast", 30, spp=0.1, prior=0.5),
        _plan(tmp_path / "slow", 30, spp=0.3, prior=1.5),
    )
    assert all(fast.steps[k] > slow.steps[k] for k in fast.steps)


def test_a_budget_too_small_is_refused_with_the_minimum_that_fits(tmp_path):
    """Before any stage: one line naming the minimum budget on this machine; nothing written. The
    minimum itself fits, and a slower machine needs more."""
    with pytest.raises(
        B.BudgetTooSmall, match=r"--budget 3 minutes cannot fit .* at least ([0-9.]+) minutes"
    ) as exc:
        _plan(tmp_path / "small", 3)
    least = exc.value.minimum
    assert isinstance(exc.value, ValueError) and 3 < least < 30 and "\n" not in str(exc.value)
    assert not (tmp_path / "small" / B.PLAN_FILE).exists()
    plan = _plan(tmp_path / "least", least)  # the minimum fits: every GS stage gets its fewest useful steps
    from coin_cl.pipeline.stage_costs import MIN_STEPS

    assert all(plan.steps[k] >= MIN_STEPS[k] - 1 for k in plan.steps)
    with pytest.raises(B.BudgetTooSmall) as slower:
        _plan(tmp_path / "slow", 3, spp=0.4, prior=1.8)
    assert slower.value.minimum > least
    assert "scene prior ~" in str(exc.value)  # its floor is part of the minimum
    # a run that trains no prior: neither counted nor named
    with pytest.raises(B.BudgetTooSmall) as untrained:
        B.plan_run(tmp_path / "untrained", {"k": 3}, 3, _NONE, None, lambda: 0.2, lambda: 0.9,
                   lambda: 0.05, shares=_REFINED, views=_VIEWS, probe_wall_seconds=5.0,
                   prior_trained=False)  # fmt: skip
    assert "scene prior" not in str(untrained.value) and untrained.value.minimum < least


def test_a_resumed_run_reuses_its_plan_without_probing(tmp_path):
    plan = _plan(tmp_path, 20)

    def never():
        raise AssertionError("probed again")

    again = B.plan_run(tmp_path, {"budget_minutes": 20, "spp": 0.2, "prior": 0.9}, 20, _NONE, None, never,
                       never, never, shares=_REFINED, views=_VIEWS)  # fmt: skip
    assert again == plan and B.read_plan(tmp_path / B.PLAN_FILE) == plan
