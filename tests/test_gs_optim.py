import math

import torch

from coin_cl.gs.optim import ExpSchedule, ParamOptimizer


def test_exp_schedule_endpoints_and_log_linear_middle():
    s = ExpSchedule(1e-2, 1e-4, 100)
    assert math.isclose(s(0), 1e-2) and math.isclose(s(100), 1e-4) and math.isclose(s(500), 1e-4)
    assert math.isclose(s(50), 1e-3, rel_tol=1e-9)
    assert ExpSchedule(0.0, 0.0)(10) == 0.0
    assert math.isclose(s.scaled(3.0)(50), 3e-3, rel_tol=1e-9)
    ramp = ExpSchedule(1.0, 1.0, 100, delay_steps=10, delay_mult=0.1)
    assert math.isclose(ramp(0), 0.1) and math.isclose(ramp(10), 1.0)


def _grads(n, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g)


def test_row_surgery_keeps_moments_aligned_with_rows():
    """Pruning rows then stepping must move the kept rows exactly as if nothing was pruned."""
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(6, 3, generator=g)
    a = ParamOptimizer({"x": x0.clone()}, {"x": 0.1})
    ref = ParamOptimizer({"x": x0.clone()}, {"x": 0.1})
    for it in range(3):
        for o in (a, ref):
            o.params["x"].grad = _grads(6, it)
            o.step(it)
    keep = torch.tensor([True, False, True, True, False, True])
    a.keep_rows(["x"], keep)
    a.append_rows({"x": torch.zeros(2, 3)})
    assert a.params["x"].shape == (6, 3)
    st = a.optims["x"].state[a.params["x"]]
    assert torch.count_nonzero(st["exp_avg"][4:]) == 0  # new rows start with zero moments
    for it in range(3, 5):
        ga = _grads(6, it)
        a.params["x"].grad = torch.cat([ga[keep], torch.zeros(2, 3)])
        a.step(it)
        ref.params["x"].grad = ga
        ref.step(it)
    assert torch.allclose(a.params["x"].data[:4], ref.params["x"].data[keep])
    assert torch.count_nonzero(a.params["x"].data[4:]) == 0  # zero grad + zero moments: no move


def test_set_rows_resets_moments_and_state_roundtrip():
    o = ParamOptimizer({"x": torch.ones(4), "frozen": torch.ones(2)}, {"x": 0.5})
    o.params["x"].grad = torch.ones(4)
    o.params["frozen"].grad = torch.ones(2)
    o.step(0)
    assert torch.equal(o.params["frozen"].data, torch.ones(2))  # no lr entry: frozen
    sd = o.state_dict()
    o.set_rows("x", torch.zeros(4))
    assert torch.count_nonzero(o.optims["x"].state[o.params["x"]]["exp_avg"]) == 0
    o2 = ParamOptimizer({"x": torch.ones(7), "frozen": torch.ones(2)}, {"x": 0.5})
    o2.load_state_dict(sd)  # different row count before loading
    assert torch.equal(o2.params["x"].data, sd["params"]["x"])
    st = o2.optims["x"].state[o2.params["x"]]
    assert torch.equal(st["exp_avg"], sd["optims"]["x"]["state"][0]["exp_avg"])


def test_fused_adam_matches_the_per_op_path():
    """The fused CPU Adam (default) and the per-op one take the same steps (rounding aside),
    schedules and frozen tensors included; the gradients set here are strided views, which torch's
    fused kernel alone would misread."""
    g = torch.Generator().manual_seed(1)
    x0, y0 = torch.randn(50, 3, generator=g), torch.randn(7, generator=g)
    opts = {}
    for fused in (False, True):
        o = ParamOptimizer({"x": x0.clone(), "y": y0.clone(), "frozen": y0.clone()},
                           {"x": ExpSchedule(0.1, 0.001, 10), "y": 0.05})  # fmt: skip
        o.fused = fused
        for it in range(10):
            o.params["x"].grad = _grads(50, it)
            o.params["y"].grad = _grads(7, it + 100)[:, 0]
            o.params["frozen"].grad = torch.ones(7)
            o.step(it)
        opts[fused] = o
    for name in ("x", "y"):
        a, b = opts[False].params[name].data, opts[True].params[name].data
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6), name
        assert not torch.equal(a, x0 if name == "x" else y0)  # it moved
    assert torch.equal(opts[True].params["frozen"].data, y0)
