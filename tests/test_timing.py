"""The timing probes' loop (coin_cl.timing), on a fake clock: no wall time is measured here."""

import pytest

from coin_cl import timing


def test_warm_up_calls_run_untimed_and_the_mean_is_of_the_timed_ones(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(timing.time, "perf_counter", lambda: clock[0])
    calls = []

    def step():
        calls.append(1)
        clock[0] += 5.0 if len(calls) == 1 else 1.0  # the first call is slow, as a kernel build is

    assert timing.mean_step_seconds(step, steps=3, warmup=1) == 1.0  # the slow first call is not in it
    assert len(calls) == 4
    with pytest.raises(ValueError, match="at least one timed step"):
        timing.mean_step_seconds(step, steps=0, warmup=1)


def test_the_median_probe_is_not_moved_by_one_slow_call(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(timing.time, "perf_counter", lambda: clock[0])
    costs = iter([9.0, 1.0, 4.0, 1.2])  # warm-up, then one timed call slowed by other work

    def step():
        clock[0] += next(costs)

    assert timing.median_step_seconds(step, steps=3, warmup=1) == pytest.approx(1.2)  # a mean: 2.07
    with pytest.raises(ValueError, match="at least one timed step"):
        timing.median_step_seconds(step, steps=0, warmup=0)


def test_late_step_seconds_is_the_rate_over_the_last_fifth():
    """A run whose steps slow down from 0.1 s to 0.3 s after step 50 of 100 (log entries every 10
    steps): the last fifth costs 0.3 s a step, the mean would say 0.2."""
    log, t = [], 0.0
    for step in range(10, 101, 10):
        t += 10 * (0.1 if step <= 50 else 0.3)
        log.append({"step": step, "train_seconds": t})
    assert timing.late_step_seconds(log) == pytest.approx(0.3)
    assert timing.late_step_seconds(log[:1]) is None  # one entry: no interval
    assert (
        timing.late_step_seconds([{"step": 5, "train_seconds": 1.0}, {"step": 5, "train_seconds": 2.0}])
        is None
    )
    assert timing.late_step_seconds([{"step": "x"}, *log]) == pytest.approx(
        0.3
    )  # a malformed entry is skipped
