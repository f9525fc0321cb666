"""The plan of a CoIn run (coin_cl.pipeline.coin_plan): the budget's rules applied to a CoInConfig
(explicit counts, the adversarial phase left out on the embedded fills, rates taken from another run)."""

import json

import numpy as np
import pytest

from coin_cl.pipeline import budget as B
from coin_cl.pipeline import coin_plan as CP
from coin_cl.pipeline import schedule as S


class _Cam:
    width, height = 64, 48


class _Scene:
    cameras = [_Cam()] * 4
    masks = [np.ones((48, 64), bool)] * 4
    # stage 1 takes a learned inpainter's fills (of a view the tests leave out of training, so that
    # stage 1's estimate is the same as with the embedded inpainter)
    priors = {"rgb": {3: "the dataset's inpaint of view 3"}}

    def __len__(self):
        return 4


class _OwnCapture(_Scene):
    priors = {}  # no dataset inpaints: stage 1 is the embedded exemplar inpainter


def _manifest(stage, seconds: float, result: dict) -> None:
    """A finished stage's manifest (as the runner writes it) recording `seconds` and `result`."""
    stage.mkdir(parents=True)
    doc = {"key": "k", "settings": {}, "outputs": {}, "seconds": seconds, "result": result}
    (stage / "manifest.json").write_text(json.dumps(doc))


def test_the_adversarial_phase_runs_only_on_a_learned_inpainters_fills(tmp_path, monkeypatch):
    """TE-D's discriminator takes stage 1's fills as the real texture: with the embedded inpainters
    (exemplar, Telea, scene prior) the plan leaves the phase out, says why in its key, and gives its
    share of the budget to the fine-tune phase, in the plan and in the re-plan from Ref-GS's rate (a
    written plan reads back the same); an explicit count runs it; dataset / LaMa fills keep it."""
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig

    monkeypatch.setattr(CP, "probe_seconds_per_step", lambda *a, **k: 0.5)
    monkeypatch.setattr(CP, "disc_probe", lambda *a: lambda: 0.1)
    monkeypatch.setattr(CP, "prior_probe", lambda *a: lambda: 0.9)
    # both with CLG's scene-prior sampler, so that both pools are the budget less the same fixed costs
    from coin_cl.pipeline.clg_config import CLGConfig

    sampler = CLGConfig(prior_sampler=True)
    lama = CP.plan_for(_Scene(), tmp_path / "lama", CoInConfig(budget_minutes=10.0, clg=sampler), [0, 1])
    own = CP.plan_for(_OwnCapture(), tmp_path / "own", CoInConfig(budget_minutes=10.0, clg=sampler), [0, 1])
    both = lama.minutes["ted_finetune"] + lama.minutes["ted_adversarial"]
    assert own.minutes["ted_finetune"] == pytest.approx(both, rel=1e-3)  # the same pool, one phase
    assert own.steps["ted_adversarial"] == 0 and own.minutes["ted_adversarial"] is None
    assert abs(own.steps["ted_finetune"] - B.stage_steps("ted_finetune", both, 0.5)) <= 1
    assert own.steps["ted_finetune"] > 2 * lama.steps["ted_finetune"]
    assert "embedded" in own.key["ted_adversarial"] and own.disc_seconds_per_step is None
    assert B.read_plan(tmp_path / "own" / B.PLAN_FILE) == own
    # Ref-GS ran exactly as planned: the fine-tune phase gets both phases' minutes at its own cost
    refgs_s = 60.0 * own.minutes["refgs"]
    _manifest(tmp_path / "own" / "2_refgs", refgs_s, {"steps": 100, "train_minutes": refgs_s / 60})
    again = S.ted_schedule(tmp_path / "own", own, 10.0).steps
    want = int(60.0 * own.minutes["ted_finetune"] / B.ted_step_seconds(own, "ted_finetune", refgs_s / 100))
    assert abs(again["ted_finetune"] - want) <= 1 and again["ted_adversarial"] == 0
    telea = CoInConfig(budget_minutes=10.0, inpaint2d=Inpaint2DConfig(inpainter="telea"))
    assert "telea" in CP.plan_for(_OwnCapture(), tmp_path / "telea", telea, [0, 1]).key["ted_adversarial"]
    asked = CoInConfig(budget_minutes=10.0, iters_ted_adversarial=9)
    assert CP.plan_for(_OwnCapture(), tmp_path / "asked", asked, [0, 1]).steps["ted_adversarial"] == 9
    assert "ted_adversarial" not in lama.key and lama.steps["ted_adversarial"] > 0
    no_dataset = CoInConfig(budget_minutes=10.0, inpaint2d=Inpaint2DConfig(use_dataset=False))
    assert CP.plan_for(_Scene(), tmp_path / "nd", no_dataset, [0, 1]).steps["ted_adversarial"] == 0


def test_ted_counts_none_follow_the_plan_and_numbers_are_honoured(tmp_path, monkeypatch):
    """TEDConfig.iters_* None: the budget plan's counts; a number is kept by the plan, by the re-plan
    from Ref-GS's measured rate, and reaches TE-D; the user's config is not changed."""
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.ted import TEDConfig

    monkeypatch.setattr(CP, "probe_seconds_per_step", lambda *a, **k: 0.5)
    monkeypatch.setattr(CP, "prior_probe", lambda *a: lambda: 0.9)
    monkeypatch.setattr(CP, "disc_probe", lambda *a: None)
    auto = CP.plan_for(_Scene(), tmp_path / "none", CoInConfig(budget_minutes=10.0), [0, 1])
    assert auto.source == "probe" and all(n > 7 for n in auto.steps.values())

    cfg = CoInConfig(budget_minutes=10.0, ted=TEDConfig(iters_finetune=7))
    plan = CP.plan_for(_Scene(), tmp_path / "seven", cfg, [0, 1])
    assert plan.steps["ted_finetune"] == 7 and plan.minutes["ted_finetune"] is None
    # the 7 steps cost less than the planned phase: the others get what it leaves
    assert all(plan.steps[k] >= auto.steps[k] for k in ("refgs", "ted_adversarial"))
    assert cfg.ted.iters_finetune == 7 and cfg.ted.iters_adversarial is None  # not overwritten
    # Ref-GS ran twice as slow as planned: TE-D's free phase is planned again, the explicit one is kept.
    slow = 2.0 * 60.0 * plan.minutes["refgs"]
    _manifest(
        tmp_path / "seven" / "2_refgs", slow, {"steps": plan.steps["refgs"], "train_minutes": slow / 60}
    )
    again = S.ted_schedule(tmp_path / "seven", plan, 10.0).steps
    assert again["ted_finetune"] == 7 and again["ted_adversarial"] < plan.steps["ted_adversarial"]
    # Both spellings may be used when they agree; disagreeing ones are an error, not a silent choice.
    both = CoInConfig(iters_ted_finetune=7, ted=TEDConfig(iters_finetune=7))
    assert CP.explicit_steps(both)["ted_finetune"] == 7
    with pytest.raises(ValueError, match="iters_ted_finetune=5 and CoInConfig.ted.iters_finetune=7"):
        CP.explicit_steps(CoInConfig(iters_ted_finetune=5, ted=TEDConfig(iters_finetune=7)))


def test_a_comparison_row_plans_with_the_rates_of_the_run_it_is_compared_to(tmp_path, monkeypatch):
    """`CoInConfig.rates_from`: the row's plan takes the GS, scene-prior and discriminator rates of
    the other run's plan instead of probing (a second probe could give the prior one step more and
    redo the stages the rows share); a rate that plan lacks is measured; a missing plan is an error
    naming it."""
    from coin_cl.pipeline.coin import CoInConfig

    monkeypatch.setattr(CP, "probe_seconds_per_step", lambda *a, **k: 0.5)
    monkeypatch.setattr(CP, "prior_probe", lambda *a: lambda: 1.31)
    monkeypatch.setattr(CP, "disc_probe", lambda *a: lambda: 0.27)
    first = CP.plan_for(_Scene(), tmp_path / "coin", CoInConfig(budget_minutes=40.0), [0, 1])
    assert first.prior_steps == round(first.prior_seconds / 1.31) > 133  # above the floor: rate-bound

    def never(*a, **k):
        raise AssertionError("probed although the rates were given")

    monkeypatch.setattr(CP, "probe_seconds_per_step", never)
    monkeypatch.setattr(CP, "prior_probe", lambda *a: never)
    monkeypatch.setattr(CP, "disc_probe", lambda *a: never)
    cfg = CoInConfig(budget_minutes=40.0, rates_from=str(tmp_path / "coin"))
    row = CP.plan_for(_Scene(), tmp_path / "row", cfg, [0, 1])
    assert (row.steps, row.prior_steps) == (first.steps, first.prior_steps)
    rates = (row.probe_seconds_per_step, row.prior_seconds_per_step, row.disc_seconds_per_step)
    assert rates == (0.5, 1.31, 0.27)
    assert row.key["rates_from"] == str(tmp_path / "coin") and "rates_from" not in first.key
    # a rate the other plan lacks is measured here
    plan = json.loads((tmp_path / "coin" / B.PLAN_FILE).read_text())
    plan["disc_seconds_per_step"] = None
    (tmp_path / "coin" / B.PLAN_FILE).write_text(json.dumps(plan))
    monkeypatch.setattr(CP, "disc_probe", lambda *a: lambda: 0.5)
    assert CP.plan_for(_Scene(), tmp_path / "row2", cfg, [0, 1]).disc_seconds_per_step == 0.5
    with pytest.raises(FileNotFoundError, match="nowhere.*plan.json"):
        CP.plan_for(_Scene(), tmp_path / "row3", CoInConfig(rates_from=str(tmp_path / "nowhere")), [0, 1])


def test_a_baseline_with_its_counts_given_plans_nothing_and_refuses_nothing(tmp_path, monkeypatch):
    """The naive baseline (TE-D and CLG skipped, Ref-GS's and the split's counts given) trains what it
    is given whatever the budget: no probe, no refusal, TE-D's phases 0 and no share for the split."""
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.refine_masks import RefineConfig

    def no_probe(*a, **k):
        raise AssertionError("a plan with every count given must not probe")

    monkeypatch.setattr(CP, "probe_seconds_per_step", no_probe)
    cfg = CoInConfig(budget_minutes=0.5, skip=("refgs", "clg", "ted"), iters_refgs=400,
                     inpaint_region="refined", refine=RefineConfig(iters=300))  # fmt: skip
    plan = CP.plan_for(_OwnCapture(), tmp_path / "naive", cfg, [0, 1])
    assert plan.source == "explicit" and "refine" not in plan.steps
    assert plan.steps == {"refgs": 400, "ted_finetune": 0, "ted_adversarial": 0}


def test_stage_one_is_costed_by_the_views_it_fills_by_computation():
    """The dataset's own fills are read, not computed: only the masked training views without one
    count towards stage 1's estimate; the embedded inpainter fills every masked view; CLG guides every
    masked view where it runs (with a sampler, or propagating the reference without one where asked,
    on any fills), and is absent when skipped or left out (the default without SD2)."""
    from coin_cl.pipeline.clg_config import CLGConfig
    from coin_cl.pipeline.coin import CoInConfig

    cfg = CoInConfig()
    views = CP.fixed_views(_Scene(), cfg, [0, 1, 2, 3])
    # a learned inpainter's fills: stage 1 reads them; no SD2, no prior_sampler: CLG left out
    assert views == {"0_scene": 4, "1_inpaint": 3, "eval": 4}
    assert CP.fixed_views(_Scene(), CoInConfig(clg=CLGConfig(prior_sampler=True)), [0, 1, 2, 3])["3_clg"] == 4
    own = CP.fixed_views(_OwnCapture(), cfg, [0, 1, 2, 3])  # the exemplar's fills
    assert own == {"0_scene": 4, "1_inpaint": 4, "eval": 4}
    warp = CoInConfig(clg=CLGConfig(without_sampler=True))  # CLG asked to propagate without a sampler
    assert CP.fixed_views(_OwnCapture(), warp, [0, 1, 2, 3]) == {**own, "3_clg_propagate": 4}
    sampled = CP.fixed_views(_OwnCapture(), CoInConfig(clg=CLGConfig(prior_sampler=True)), [0, 1, 2, 3])
    assert sampled == {"0_scene": 4, "1_inpaint": 4, "3_clg": 4, "eval": 4}
    assert CP.fixed_views(_OwnCapture(), CoInConfig(sd_path="SD2"), [0, 1, 2, 3])["3_clg"] == 4
    assert CP.fixed_views(_OwnCapture(), cfg, [0, 1, 2])["1_inpaint"] == 3
    assert "3_clg" not in CP.fixed_views(_Scene(), CoInConfig(skip=("clg",)), [0, 1])
    # an insertion that lifts its object leaves CLG out (coin_plan.clg_skip_reason): nothing priced
    edited = np.zeros((2, 2, 3), np.float32)
    assert "3_clg" not in CP.fixed_views(_Scene(), cfg, [0, 1], edited)
    assert "3_clg" not in CP.fixed_views(_Scene(), CoInConfig(prompt="a red box", sd_path="SD2"), [0, 1])
    # below the capture's size eval also scores the masked test views there
    held = type("Held", (_OwnCapture,), {"test_idx": [3]})()
    assert CP.fixed_views(held, CoInConfig(resolution=0.5), [0, 1])["eval_capture"] == 1
    assert "eval_capture" not in CP.fixed_views(held, CoInConfig(resolution=1.0), [0, 1])


def test_a_removal_without_a_sampler_leaves_clg_out_unless_asked():
    """No SD2 and no prior sampler: CLG would only propagate the reference, which scored below
    leaving it out on real scenes; it is left out with the reason, and runs where a sampler does,
    where `without_sampler` asks, or where an insertion's CLG carries its object."""
    from coin_cl.pipeline.clg_config import CLGConfig
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.insert_config import InsertConfig

    why = CP.clg_skip_reason(CoInConfig(), None)
    assert why.startswith("no sampler") and "without_sampler" in why
    assert CP.clg_skip_reason(CoInConfig(clg=CLGConfig(without_sampler=True)), None) is None
    assert CP.clg_skip_reason(CoInConfig(clg=CLGConfig(prior_sampler=True)), None) is None
    assert CP.clg_skip_reason(CoInConfig(sd_path="SD2"), None) is None
    # with a sampler asked but CLGConfig.sample off there is still none to run
    assert CP.clg_skip_reason(CoInConfig(clg=CLGConfig(prior_sampler=True, sample=False)), None)
    assert CP.clg_skip_reason(CoInConfig(skip=("clg",)), None).startswith("asked")
    old_insert = CoInConfig(insert=InsertConfig(propagate=False))  # CLG warps the edited reference
    assert CP.clg_skip_reason(old_insert, np.zeros((2, 2, 3), np.float32)) is None


def test_no_time_is_planned_for_a_scene_prior_nothing_trains(tmp_path, monkeypatch, caplog):
    """CLG skipped, left out (the default without SD2) or propagating without a sampler, and stage 1
    filling without the prior (the embedded exemplar inpainter): the prior's steps are still planned
    (stage 1's key holds them) but its seconds go to the GS stages and the refusal's minimum leaves it
    out; with CLG sampling with it, or the prior as stage 1's inpainter, it is charged as before."""
    from coin_cl.pipeline.clg_config import CLGConfig
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig

    monkeypatch.setattr(CP, "probe_seconds_per_step", lambda *a, **k: 0.5)
    monkeypatch.setattr(CP, "disc_probe", lambda *a: lambda: 0.1)
    monkeypatch.setattr(CP, "prior_probe", lambda *a: lambda: 0.9)
    sampler = CLGConfig(prior_sampler=True)
    both = CP.plan_for(_OwnCapture(), tmp_path / "a", CoInConfig(budget_minutes=10.0, clg=sampler), [0, 1])
    warp = CoInConfig(budget_minutes=10.0, clg=CLGConfig(without_sampler=True))
    propagating = CP.plan_for(_OwnCapture(), tmp_path / "f", warp, [0, 1])
    assert "prior" not in propagating.fixed_seconds
    assert propagating.fixed_seconds["3_clg"] < both.fixed_seconds["3_clg"]  # a warp and a blend a view
    assert propagating.minutes["refgs"] > both.minutes["refgs"]
    default = CP.plan_for(_OwnCapture(), tmp_path / "g", CoInConfig(budget_minutes=10.0), [0, 1])
    assert "prior" not in default.fixed_seconds and "3_clg" not in default.fixed_seconds  # left out
    assert default.minutes["refgs"] > propagating.minutes["refgs"]
    with caplog.at_level("INFO"):
        bare = CP.plan_for(
            _OwnCapture(), tmp_path / "b", CoInConfig(budget_minutes=10.0, skip=("clg",)), [0, 1]
        )
    assert "prior" in both.fixed_seconds and "prior" not in bare.fixed_seconds
    assert bare.prior_steps == both.prior_steps and "not trained here" in caplog.text
    assert bare.minutes["refgs"] > both.minutes["refgs"]
    own = CoInConfig(budget_minutes=10.0, skip=("clg",), inpaint2d=Inpaint2DConfig(inpainter="prior"))
    assert "prior" in CP.plan_for(_OwnCapture(), tmp_path / "c", own, [0, 1]).fixed_seconds
    with pytest.raises(B.BudgetTooSmall) as tiny_with:
        CP.plan_for(_OwnCapture(), tmp_path / "d", CoInConfig(budget_minutes=0.5, clg=sampler), [0, 1])
    with pytest.raises(B.BudgetTooSmall) as tiny_without:
        CP.plan_for(_OwnCapture(), tmp_path / "e", CoInConfig(budget_minutes=0.5, skip=("clg",)), [0, 1])
    assert tiny_without.value.minimum < tiny_with.value.minimum
