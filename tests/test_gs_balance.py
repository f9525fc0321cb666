"""The auxiliary terms' cap (coin_cl.gs.balance): a term whose gradient is k times the photometric's
is scaled to ratio / (k sqrt(f)) (f: the share of steps it is active on), never above 1; a term below
the cap and a ratio of 0 leave everything as it was; the state resumes exactly; in the trainer an
uncapped depth-like term fills Adam's second moment and the capped one does not."""

from __future__ import annotations

import math

import pytest
import torch

from coin_cl.gs.balance import AuxBalance, grad_norm
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.terms import LossContext, LossTerm, PhotometricLoss
from coin_cl.gs.trainer import TrainConfig, Trainer


def _values(p: torch.Tensor, k: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A main part with gradient norm |a| and an auxiliary part with gradient norm k |a| in p."""
    a = torch.tensor([3.0, 4.0])
    return (a * p).sum(), k * (a.flip(0) * p).sum()


def test_grad_norm_is_the_norm_over_all_parameters_and_keeps_the_graph():
    p, q = torch.ones(2, requires_grad=True), torch.ones(3, requires_grad=True)
    v = (torch.tensor([3.0, 4.0]) * p).sum() + 12.0 * q[0]
    assert grad_norm(v, [p, q]) == pytest.approx(13.0)
    v.backward()  # the graph is still there for the step
    assert p.grad.tolist() == [3.0, 4.0]


@pytest.mark.parametrize("k", [10.0, 80.0])
def test_a_term_active_on_every_step_is_scaled_to_ratio_over_k(k: float):
    p = torch.ones(2, requires_grad=True)
    bal = AuxBalance(ratio=1.0, every=5)
    main, aux = _values(p, k)
    out = bal.weigh(0, main, {"depth": aux}, [p])
    assert bal.scale["depth"] == pytest.approx(1.0 / k)
    assert float(out["depth"].detach()) == pytest.approx(float(aux.detach()) / k)
    assert grad_norm(out["depth"], [p]) == pytest.approx(grad_norm(main, [p]))


def test_a_term_active_on_one_step_in_n_may_be_sqrt_n_times_larger():
    p = torch.ones(2, requires_grad=True)
    bal = AuxBalance(ratio=1.0, every=1)
    for step in range(16):
        main, aux = _values(p, 40.0)
        live = aux if step % 4 == 3 else torch.zeros(())  # no graph: not active
        bal.weigh(step, main, {"depth": live}, [p])
    assert bal.active["depth"] == 4
    # its last measurement at step 15 saw it active on 4 of 16 steps: f = 1/4
    assert bal.scale["depth"] == pytest.approx(1.0 / (40.0 * math.sqrt(0.25)))


def test_a_term_below_the_cap_and_a_zero_ratio_change_nothing():
    p = torch.ones(2, requires_grad=True)
    main, aux = _values(p, 0.5)
    bal = AuxBalance(ratio=1.0)
    out = bal.weigh(0, main, {"depth": aux}, [p])["depth"]
    assert float(out.detach()) == float(aux.detach()) and bal.scale["depth"] == 1.0
    main, aux = _values(p, 100.0)
    off = AuxBalance(ratio=0.0)
    assert off.weigh(0, main, {"depth": aux}, [p])["depth"] is aux
    assert off.state_dict()["scale"] == {} and off.measured_at == {}


def test_measurements_come_every_n_active_steps_and_the_state_resumes():
    p = torch.ones(2, requires_grad=True)
    bal = AuxBalance(ratio=2.0, every=3)
    ks = [10.0, 20.0, 40.0, 5.0, 5.0, 5.0, 8.0]

    def step(b: AuxBalance, i: int) -> float:
        main, aux = _values(p, ks[i])
        return float(b.weigh(i, main, {"t": aux}, [p])["t"].detach())

    for i in range(4):
        step(bal, i)
    assert bal.measured_at["t"] == 3  # steps 0 and 3; 1 and 2 kept step 0's scale
    copy = AuxBalance(ratio=2.0, every=3)
    copy.load_state_dict(bal.state_dict())
    assert [step(bal, i) for i in range(4, 7)] == [step(copy, i) for i in range(4, 7)]
    # the scale follows the exponential means of the squared norms, never above 1
    assert 0 < bal.scale["t"] <= 1.0


def test_a_measurement_leaves_retained_gradients_as_the_step_alone_would():
    p = torch.ones(2, requires_grad=True)
    y = p * 2.0  # the screen-space means: a non-leaf tensor whose .grad the densification reads
    y.retain_grad()
    main, aux = (torch.tensor([3.0, 4.0]) * y).sum(), 50.0 * (y**2).sum()
    out = AuxBalance(ratio=1.0).weigh(0, main, {"depth": aux}, [p], retained=[y])
    assert y.grad is None
    (main + out["depth"]).backward()
    expect = torch.tensor([3.0, 4.0]) + out["depth"].detach() / aux.detach() * 100.0 * y.detach()
    assert torch.allclose(y.grad, expect)


@pytest.mark.parametrize("ratio, every", [(-1.0, 5), (float("nan"), 5), (1.0, 0)])
def test_bad_settings_are_clear_errors(ratio: float, every: int):
    with pytest.raises(ValueError, match="aux_grad_ratio|aux_measure_every"):
        AuxBalance(ratio, every)


class _LoudDepth(LossTerm):
    """A depth-like prior: pulls the rendered depth towards twice itself, weighted 1000."""

    name = "loud_depth"
    auxiliary = True
    weight = 1000.0

    def before_render(self, view, index, step, model):
        return {"return_depth": True}

    def __call__(self, ctx: LossContext) -> torch.Tensor:
        d = ctx.out.depth
        return (d - 2.0 * d.detach()).abs().mean()


def _train(scene, ratio: float, iters: int = 20) -> Trainer:
    from coin_cl.gs.model_kinds import build_model
    from coin_cl.gs.strategy import ScaffoldStrategy

    m = build_model("scaffold", scene.noisy_points(), None, 3.5, seed=0)
    cfg = TrainConfig(iters=iters, backend="torch", progress=False, log_every=5, export_ply=False,
                      aux_grad_ratio=ratio, aux_measure_every=5)  # fmt: skip
    strategy = ScaffoldStrategy(update_until=0, gaussians_per_pixel=0.0)
    tr = Trainer(
        m, scene.views[1:], [], cfg, None, strategy=strategy, terms=[PhotometricLoss(), _LoudDepth()]
    )
    tr.train()
    return tr


def test_in_the_trainer_an_uncapped_prior_fills_adams_moment_and_a_capped_one_does_not():
    scene = tiny_scene(n=30, width=24, height=16, n_views=6, backend="torch")
    capped, loud = _train(scene, 1.0), _train(scene, 0.0)

    def rms_v(tr: Trainer) -> float:
        st = tr.model.optimizer.state_dict()["optims"]["mlp_opacity.0.weight"]["state"][0]
        return float(st["exp_avg_sq"].mean().sqrt())

    assert 0 < capped.balance.scale["loud_depth"] < 0.05
    assert loud.balance.scale == {}
    assert rms_v(loud) > 5 * rms_v(capped)
    assert capped.log["train"][-1]["loud_depth_scale"] == pytest.approx(capped.balance.scale["loud_depth"])
