"""`coin_cl.gs.model_kinds`: building a model by kind name, the published schedules scaled to a
run, and rebuilding a model from its checkpoint state."""

import numpy as np
import pytest
import torch

from coin_cl.gs.gaussians import GaussianConfig
from coin_cl.gs.model_kinds import (
    MODELS,
    build_model,
    continue_rates,
    model_from_state,
    scaled_model_config,
    scaled_strategy,
)
from coin_cl.gs.scaffold import ScaffoldConfig
from coin_cl.gs.strategy import DefaultStrategy, ScaffoldStrategy, default_strategy


def test_scaled_strategy_matches_the_published_schedule():
    assert scaled_strategy("3dgs", 30_000) == default_strategy("3dgs") == DefaultStrategy()
    assert scaled_strategy("scaffold", 60_000) == ScaffoldStrategy()
    d = scaled_strategy("3dgs", 3000)
    assert (d.refine_every, d.refine_start, d.refine_stop, d.reset_every) == (20, 100, 1500, 600)
    s = scaled_strategy("scaffold", 3000)
    assert (s.update_interval, s.start_stat, s.update_from, s.update_until) == (20, 50, 150, 1500)


def test_scaled_model_config_compresses_the_published_schedule():
    assert scaled_model_config("3dgs", 30_000) == GaussianConfig()
    assert scaled_model_config("scaffold", 30_000) == ScaffoldConfig()
    g = scaled_model_config("3dgs", 3000)
    assert (g.lr_means.max_steps, g.sh_degree_interval) == (3000, 100)
    s = scaled_model_config("scaffold", 3000)
    lrs = (s.lr_offsets, s.lr_mlp_opacity, s.lr_mlp_cov, s.lr_mlp_color)
    assert [lr.max_steps for lr in lrs] == [3000] * 4


@pytest.mark.parametrize("kind", MODELS)
def test_model_from_state_rebuilds_the_same_model(kind):
    pts = np.random.default_rng(0).uniform(-1, 1, (40, 3))
    m = build_model(kind, pts, None, extent=2.0, seed=3)
    assert m.kind == kind
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():  # values no fresh model has, so they must come from the state
        for name, p in m.optimizer.params.items():
            if name != "anchors":  # anchors are re-voxelised on rebuild: keep them on the grid
                p.add_(0.1 * torch.randn(p.shape, generator=gen))
    r = model_from_state(m.state_dict())
    assert type(r) is type(m) and r.cfg == m.cfg and r.n_primitives == m.n_primitives
    assert r.optimizer.params.keys() == m.optimizer.params.keys()
    for name, p in m.optimizer.params.items():
        assert torch.equal(r.optimizer.params[name], p), name


@pytest.mark.parametrize("kind", MODELS)
def test_continued_rates_go_on_from_where_the_schedule_stood_and_survive_a_checkpoint(kind):
    pts = np.random.default_rng(0).uniform(-1, 1, (40, 3))
    # extent 2.7: a power of two would scale the rates exactly and hide a rounding difference
    m = build_model(kind, pts, None, extent=2.7, seed=3, model_cfg=scaled_model_config(kind, 500))
    names = list(m.optimizer.lrs)
    at = {n: m.optimizer.lr(n, 200) for n in names}
    final = {n: m.optimizer.lr(n, 500) for n in names}
    decaying = [n for n in names if m.optimizer.lr(n, 0) != final[n]]
    assert decaying  # offsets / means and the MLPs decay: without them this test is empty
    continue_rates(m, 200, 300)  # the next trainer counts from 0 where this schedule stood at 200
    for n in names:
        assert m.optimizer.lr(n, 0) == pytest.approx(at[n], rel=1e-12), n
        assert m.optimizer.lr(n, 300) == pytest.approx(final[n], rel=1e-12), n
        # 300 more steps of the same log-linear decay: the one schedule's step 350 at step 150
        assert m.optimizer.lr(n, 150) == pytest.approx(at[n] ** 0.5 * final[n] ** 0.5, rel=1e-9), n
    r = model_from_state(m.state_dict())  # a resumed fine-tune keeps them, to the last bit
    assert r.cfg == m.cfg
    for n in names:
        steps = (0, 150, 300)
        assert [r.optimizer.lr(n, k) for k in steps] == [m.optimizer.lr(n, k) for k in steps], n


def test_unknown_kind_is_a_clear_error():
    pts = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"unknown model 'nerf': use one of \('scaffold', '3dgs'\)"):
        build_model("nerf", pts, None, 1.0)
    with pytest.raises(ValueError, match="unknown model 'nerf'"):
        scaled_model_config("nerf", 100)
    with pytest.raises(ValueError, match="unknown model 'nerf'"):
        scaled_strategy("nerf", 100)
    with pytest.raises(ValueError, match="checkpoint holds an unknown model kind 'nerf'"):
        model_from_state({"kind": "nerf", "optimizer": {"params": {}}})
