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
