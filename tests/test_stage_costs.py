"""What the stages cost (coin_cl.pipeline.stage_costs): the fixed stages' estimates, the machine
factor, the GS pool's split and the minimum budget."""

import doctest

import pytest

from coin_cl.pipeline import stage_costs as C


def test_fixed_costs_grow_with_views_and_a_slower_machine():
    views = {"0_scene": 20, "1_inpaint": 17, "3_clg": 17, "eval": 20}
    base = C.fixed_costs(views, 1.0)
    assert set(base) == set(views)  # no prior probed: no prior entry
    more = C.fixed_costs({k: 3 * n for k, n in views.items()}, 1.0)
    slow = C.fixed_costs(views, 2.0)
    for k in views:
        assert more[k] > base[k] > 0 and slow[k] == pytest.approx(2 * base[k])
    with_prior = C.fixed_costs(views, 1.0, prior_steps=133, prior_seconds_per_step=0.9)
    assert with_prior["prior"] == pytest.approx(133 * 0.9 * C.PRIOR_STEP_COST)
    assert "3_clg" not in C.fixed_costs({"0_scene": 20, "eval": 20}, 1.0)  # a stage left out costs nothing


def test_per_view_seconds_follow_the_views_pixels_except_the_samplers():
    views = {"0_scene": 20, "1_inpaint": 17, "3_clg": 17, "eval": 20}
    ref = C.fixed_costs(views, 1.0)
    assert C.fixed_costs(views, 1.0, view_pixels=C.REFERENCE_PIXELS) == ref
    big = C.fixed_costs(views, 1.0, view_pixels=4 * C.REFERENCE_PIXELS)
    for k, n in views.items():
        base, per_view, exponent = C.FIXED_COSTS[k]
        assert big[k] == pytest.approx(base + per_view * n * 4**exponent)
    # stage 1's fills measured 3.7x at 4x the pixels; the sampler's 64-px draws do not grow
    assert big["1_inpaint"] > 3.5 * ref["1_inpaint"] - 3.5 * C.FIXED_COSTS["1_inpaint"][0]
    assert big["3_clg"] == ref["3_clg"]
    small = C.fixed_costs({"3_clg_propagate": 17}, 1.0, view_pixels=C.REFERENCE_PIXELS // 4)
    assert small["3_clg"] < C.fixed_costs({"3_clg_propagate": 17}, 1.0)["3_clg"]
    for bad in (0, -5):
        with pytest.raises(ValueError, match="pixels"):
            C.fixed_costs(views, 1.0, view_pixels=bad)


def test_scoring_at_the_capture_size_is_part_of_evals_estimate():
    views = {"0_scene": 10, "eval": 10}
    plain = C.fixed_costs(views, 2.0)
    more = C.fixed_costs({**views, "eval_capture": 4}, 2.0)
    assert set(more) == set(plain) and more["0_scene"] == plain["0_scene"]
    assert more["eval"] == pytest.approx(plain["eval"] + 2.0 * 4 * C.CAPTURE_SECONDS_PER_VIEW)


def test_machine_factor_is_the_prior_rate_against_the_reference_within_bounds():
    assert C.machine_factor(None) == 1.0
    assert C.machine_factor(C.REFERENCE_PRIOR_SECONDS_PER_STEP * 2) == pytest.approx(2.0)
    assert C.machine_factor(1e-6) == C.FACTOR_RANGE[0] and C.machine_factor(1e6) == C.FACTOR_RANGE[1]
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="seconds per step"):
            C.machine_factor(bad)


def test_the_pool_splits_by_weight_and_never_below_zero():
    split = C.split_seconds(100.0, {"refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.0})
    assert split["refgs"] == pytest.approx(100 * 0.35 / 0.55) and split["ted_adversarial"] == 0.0
    assert sum(split.values()) == pytest.approx(100.0)
    assert C.split_seconds(-5.0, {"refgs": 1.0}) == {"refgs": 0.0}  # overran: nothing, not negative
    # floors first (the fewest useful steps), the rest by weight; a pool under them scales them down
    floors = {"refgs": 30.0, "ted_finetune": 10.0, "ted_adversarial": 50.0}
    split = C.split_seconds(100.0, {"refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.0}, floors)
    assert split == pytest.approx({"refgs": 30 + 60 * 0.35 / 0.55, "ted_finetune": 10 + 60 * 0.2 / 0.55,
                                   "ted_adversarial": 0.0})  # fmt: skip
    assert C.split_seconds(20.0, {"refgs": 1.0, "ted_finetune": 1.0}, floors) == pytest.approx(
        {"refgs": 15.0, "ted_finetune": 5.0}
    )


def test_minimum_budget_is_the_smallest_that_leaves_the_minimum_pool():
    shares = {"refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.3}
    rates = {"refgs": 0.5, "ted_finetune": 0.4, "ted_adversarial": 0.6}
    pool = C.minimum_pool(shares, rates)
    # every stage gets at least its MIN_STEPS from that pool
    assert pool == pytest.approx(sum(C.MIN_STEPS[k] * rates[k] for k in shares))
    for k, s in C.split_seconds(pool, shares, C.min_floors(shares, rates)).items():
        assert s / rates[k] >= C.MIN_STEPS[k] - 1e-9
    fixed, floor, share = 90.0, 180.0, 0.225
    least = C.minimum_budget(fixed, floor, share, pool)
    prior = max(floor, share * 60 * least)
    assert 60 * least == pytest.approx(fixed + prior + pool)
    # large fixed costs: the prior's share is above its floor and still fits
    big = C.minimum_budget(3000.0, floor, share, pool)
    assert 60 * big == pytest.approx(3000.0 + share * 60 * big + pool)


def test_the_docstring_examples_hold():
    assert doctest.testmod(C).failed == 0
