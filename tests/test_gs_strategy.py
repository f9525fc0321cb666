import logging
import math

import numpy as np
import pytest
import torch

from coin_cl.gs.base import RenderOutput, inverse_sigmoid
from coin_cl.gs.gaussians import GaussianModel
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel
from coin_cl.gs.strategy import DefaultStrategy, ScaffoldStrategy, Strategy, neural_gaussian_cap
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer


def _model(n: int = 10) -> GaussianModel:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (n, 3))
    return GaussianModel(pts, None, extent=1.0)


def _set(m: GaussianModel, name: str, value: torch.Tensor) -> None:
    m.optimizer.set_rows(name, value)


def test_densify_counts_on_fixed_inputs():
    st = DefaultStrategy(refine_start=0, refine_every=10, reset_every=1000, grow_grad2d=2e-4,
                         grow_scale3d=0.01, prune_opa=0.005)  # fmt: skip
    m = _model()
    st.initialize(m, seed=0)
    small, large = math.log(0.005), math.log(0.05)
    _set(m, "scales", torch.tensor([small] * 5 + [large] * 5)[:, None].repeat(1, 3))
    opa = torch.full((10,), 0.5)
    opa[[2, 8]] = 0.001  # below prune_opa, and low gradient: pruned
    _set(m, "opacities", inverse_sigmoid(opa))
    high = torch.zeros(10, dtype=torch.bool)
    high[[0, 1, 5, 6, 7]] = True
    st.count = torch.full((10,), 4.0)
    st.grad2d = torch.where(high, 4 * 1e-3, 4 * 1e-5)  # mean 1e-3 vs 1e-5 against 2e-4
    parent_means = m.p["means"].data[[5, 6, 7]].clone()
    ev = st.refine(m, step=9)  # the 10th completed step
    assert ev == {"cloned": 2, "split": 3, "pruned": 2, "reset": 0}
    assert m.n_primitives == 10 + 2 + 3 - 2
    for name in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        assert m.p[name].shape[0] == 13
        ost = m.optimizer.optims[name].state
        assert all(v["exp_avg"].shape[0] == 13 for v in ost.values())
    assert st.grad2d.shape == (13,) and float(st.grad2d.sum()) == 0.0  # statistics restart
    assert st.count.shape == (13,) and st.max_radii.shape == (13,)
    # Split children: scale / 1.6, near their parent (within 4 sigma of the parent's scale).
    children = m.p["means"].data[-6:]
    assert torch.allclose(torch.exp(m.p["scales"].data[-6:]), torch.full((6, 3), 0.05 / 1.6))
    dist = (children[:, None] - parent_means[None]).norm(dim=-1).amin(1)
    assert bool((dist < 4 * 0.05 * math.sqrt(3)).all())


def test_no_refinement_off_schedule_and_opacity_reset():
    st = DefaultStrategy(refine_start=50, refine_every=10, reset_every=30, prune_scale3d=0.1)
    m = _model()
    st.initialize(m)
    st.grad2d = torch.full((10,), 1.0)
    st.count = torch.ones(10)
    assert st.refine(m, step=19) == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}  # s=20 < start
    ev = st.refine(m, step=29)  # s = 30: reset only
    assert ev["reset"] == 1 and ev["cloned"] == 0
    assert float(torch.sigmoid(m.p["opacities"].data).max()) <= 0.01 + 1e-6
    # After the first reset, Gaussians larger than prune_scale3d x extent are pruned.
    st2 = DefaultStrategy(refine_start=0, refine_every=10, reset_every=30, grow_grad2d=1.0)
    m2 = _model()
    st2.initialize(m2)
    sc = torch.full((10, 3), math.log(0.01))
    sc[[3, 4]] = math.log(0.5)
    _set(m2, "scales", sc)
    assert st2.refine(m2, step=39)["pruned"] == 2  # s = 40 > reset_every


def _fake_render(m: GaussianModel, grad_px: torch.Tensor, radii: torch.Tensor) -> RenderOutput:
    """A render whose means2d carries a given pixel-space gradient [N, 2], image 20 x 10 px."""
    means2d = torch.zeros(m.n_primitives, 2, requires_grad=True)
    means2d.grad = grad_px
    meta = {"means2d": means2d, "radii": radii, "width": 20, "height": 10}
    return RenderOutput(torch.zeros(10, 20, 3), torch.zeros(10, 20), None, meta)


def test_default_strategy_statistics_in_ndc_units_and_stop():
    st = DefaultStrategy(refine_start=100, refine_stop=50)
    m = _model(4)
    st.initialize(m)
    g = torch.tensor([[1.0, 0.0], [0.0, 1.0], [3.0, 4.0], [9.0, 9.0]])
    radii = torch.tensor([2, 3, 5, 0])
    assert st.step_post_backward(m, 0, _fake_render(m, g, radii)) == {
        "cloned": 0, "split": 0, "pruned": 0, "reset": 0}  # fmt: skip
    # NDC: x times W/2 = 10, y times H/2 = 5; the invisible one (radius 0) gathers nothing.
    assert torch.allclose(st.grad2d, torch.tensor([10.0, 5.0, math.hypot(30, 20), 0.0]))
    assert torch.equal(st.count, torch.tensor([1.0, 1.0, 1.0, 0.0]))
    assert torch.equal(st.max_radii, torch.tensor([2.0, 3.0, 5.0, 0.0]))
    st.step_post_backward(m, 50, _fake_render(m, g, radii))  # at refine_stop: no statistics
    assert torch.equal(st.count, torch.tensor([1.0, 1.0, 1.0, 0.0]))


def test_strategy_state_roundtrip_and_sanity():
    m = _model()
    st = DefaultStrategy(refine_every=7)
    st.initialize(m, seed=3)
    st.grad2d += 2.0
    sd = st.state_dict()
    other = DefaultStrategy()
    other.initialize(m, seed=9)
    other.load_state_dict(sd)
    assert other.refine_every == 7  # the checkpoint's schedule wins
    assert torch.equal(other.grad2d, st.grad2d) and other.grad2d is not st.grad2d
    assert torch.equal(torch.rand(3, generator=other.gen), torch.rand(3, generator=st.gen))
    with pytest.raises(ValueError, match="anchor model"):
        ScaffoldStrategy().initialize(m)
    sm = ScaffoldModel(np.random.default_rng(0).uniform(-1, 1, (50, 3)), None, 1.0)
    with pytest.raises(ValueError, match="3DGS model"):
        DefaultStrategy().initialize(sm)
    # The base strategy keeps the primitives fixed.
    base = Strategy()
    base.initialize(sm)
    assert base.step_post_backward(sm, 0, _fake_render(m, torch.zeros(10, 2), torch.ones(10))) == {}


def _two_cell_model(st: ScaffoldStrategy) -> ScaffoldModel:
    """20 anchors on a line whose offset slot 0 points into one of two empty cells, (3, 7, 0)
    (anchors 0-9, gradient 1e-3) and (4, -6, 2) (anchors 10-19, gradient 2e-3), with statistics
    that make both grow and anchors 18 and 19 be pruned; `st` initialised on it."""
    cfg = ScaffoldConfig(voxel_size=1.0)
    pts = np.stack([np.arange(20.0), np.zeros(20), np.zeros(20)], 1)
    m = ScaffoldModel(pts, None, 1.0, cfg, seed=0)
    st.initialize(m, seed=0)
    a, k = 20, 10
    assert m.n_anchors == a
    anchors = m.p["anchors"].data
    off = torch.zeros(a, k, 3)
    off[:10, 0] = torch.tensor([3.0, 7.0, 0.0]) - anchors[:10]  # group 1 -> empty cell (3, 7, 0)
    off[10:, 0] = torch.tensor([4.0, -6.0, 2.0]) - anchors[10:]  # group 2 -> empty cell (4, -6, 2)
    off[:, 1] = torch.tensor([0.0, 0.0, 0.2])  # high gradient, own (occupied) cell
    off[:, 2] = torch.tensor([0.0, 9.0, 9.0])  # empty cells, low gradient
    off[:, 3] = torch.tensor([0.0, -9.0, -9.0])  # empty cells, high gradient, seen too rarely
    m.optimizer.set_rows("offsets", off)
    m.optimizer.set_rows("scaling", torch.zeros(a, 6))  # offsets in world units
    feats = torch.zeros(a, 32)
    feats[:10], feats[10:] = 1.0, -2.0
    m.optimizer.set_rows("features", feats)
    denom = torch.full((a, k), 50.0)  # > 100 * 0.8 * 0.5
    denom[:, 3] = 10.0
    grad = torch.full((a, k), 1e-5)
    grad[:, [0, 1, 3]] = 1e-3
    grad[10:, 0] = 2e-3  # group 2's cell is the steeper one
    st.offset_denom, st.offset_grad_accum = denom.reshape(-1), (grad * denom).reshape(-1)
    st.anchor_denom = torch.full((a,), 100.0)
    st.opacity_accum = torch.full((a,), 50.0)
    st.opacity_accum[[18, 19]] = 0.1  # mean 0.001 < min_opacity: pruned
    return m


def _grower(**kw) -> ScaffoldStrategy:
    return ScaffoldStrategy(update_depth=1, update_init_factor=1, update_interval=100,
                            success_threshold=0.8, grad_threshold=2e-4, min_opacity=0.005, **kw)  # fmt: skip


def test_anchor_growing_and_pruning_counts():
    st = _grower()
    m = _two_cell_model(st)
    k = 10
    ev = st.adjust_anchors(m)
    assert ev == {"grown": 2, "pruned": 2, "held_back": 0}
    assert m.n_anchors == 20
    new = m.p["anchors"].data[-2:]
    assert {tuple(r) for r in new.tolist()} == {(3.0, 7.0, 0.0), (4.0, -6.0, 2.0)}
    by_cell = {tuple(r): f for r, f in zip(new.tolist(), m.p["features"].data[-2:], strict=True)}
    assert torch.all(by_cell[(3.0, 7.0, 0.0)] == 1.0) and torch.all(by_cell[(4.0, -6.0, 2.0)] == -2.0)
    assert torch.count_nonzero(m.p["offsets"].data[-2:]) == 0
    assert torch.allclose(m.p["scaling"].data[-2:], torch.zeros(2, 6))  # log(voxel x 1)
    for name in ("offsets", "features", "scaling"):
        ost = next(iter(m.optimizer.optims[name].state.values()), None)
        assert m.p[name].shape[0] == 20 and (ost is None or ost["exp_avg"].shape[0] == 20)
    assert st.offset_denom.shape == (20 * k,) and st.opacity_accum.shape == (20,)
    # The statistics that were used are reset; the rarely-seen slot keeps accumulating.
    assert float(st.offset_denom.view(20, k)[:18, 0].sum()) == 0.0
    assert float(st.offset_denom.view(20, k)[:18, 3].sum()) == 18 * 10.0


def test_neural_gaussian_cap_is_per_pixel_times_pixels():
    assert neural_gaussian_cap(0.25, 1000) == 250
    assert neural_gaussian_cap(0.1, 4_866_624) == 486_662  # floor
    assert neural_gaussian_cap(0.0, 1000) == 0 and neural_gaussian_cap(0.5, 0) == 0  # no cap
    st = ScaffoldStrategy(gaussians_per_pixel=0.25)
    m = ScaffoldModel(np.eye(3), None, 1.0, ScaffoldConfig(voxel_size=0.5))
    st.initialize(m, train_pixels=1234)
    lim = st.size_limit(m)
    # 0.25 x 1234 = 308.5 -> 308 neural Gaussians; whole anchors of 10 offsets: 30.
    assert lim == {"anchors": 30, "neural_gaussians": 300,
                   "reason": "cap 308 = 0.25 per training pixel x 1234 pixels"}  # fmt: skip
    st.initialize(m)  # pixels unknown: only the memory guard
    assert st.size_limit(m)["anchors"] == st.max_anchors
    st.max_anchors = 7  # the smaller of the two wins
    st.initialize(m, train_pixels=1234)
    assert st.size_limit(m)["anchors"] == 7 and "max_anchors" in st.size_limit(m)["reason"]


def test_anchor_growth_under_the_cap_keeps_the_steepest_cell():
    # Room for one new anchor (20 anchors, cap 21 x 10): the steeper cell grows, the other waits.
    st = _grower(gaussians_per_pixel=1.0)
    m = _two_cell_model(st)
    st.train_pixels = 210
    ev = st.adjust_anchors(m)
    assert ev == {"grown": 1, "pruned": 2, "held_back": 1}
    assert m.p["anchors"].data[-1].tolist() == [4.0, -6.0, 2.0]


def test_a_model_built_above_its_cap_does_not_grow_and_says_so(caplog):
    st = _grower(gaussians_per_pixel=1.0)
    m = _two_cell_model(st)
    st.train_pixels = 100  # cap 10 anchors; the model has 20
    with caplog.at_level(logging.INFO, logger="coin_cl.gs.strategy"):
        ev = st.adjust_anchors(m)
    assert ev == {"grown": 0, "pruned": 2, "held_back": 2}
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "cap 100 = 1 per training pixel x 100 pixels" in msg and "starts above the cap" in msg


def test_a_floor_lets_a_model_built_above_its_per_pixel_cap_grow_to_it(caplog):
    # The same model and per-pixel cap (10 anchors; the model has 20), with a floor of 21 anchors
    # (`min_cap`, what Ref-GS sets from its initial size): room for one, the steeper cell grows.
    st = _grower(gaussians_per_pixel=1.0)
    m = _two_cell_model(st)
    st.train_pixels = 100
    st.min_cap = 210
    lim = st.size_limit(m)
    assert lim["anchors"] == 21 and lim["reason"] == (
        "cap 210 (the caller's floor, min_cap) over the per-pixel cap 100 = 1 per training pixel x 100 pixels"
    )
    with caplog.at_level(logging.INFO, logger="coin_cl.gs.strategy"):
        ev = st.adjust_anchors(m)
    assert ev == {"grown": 1, "pruned": 2, "held_back": 1}
    assert m.p["anchors"].data[-1].tolist() == [4.0, -6.0, 2.0]
    st.min_cap, st.gaussians_per_pixel = 5000, 0.0  # no per-pixel cap: the floor adds none
    assert st.size_limit(m)["anchors"] == st.max_anchors


@pytest.mark.parametrize("cap", [0.0, 0.2])
def test_scaffold_run_never_exceeds_its_cap_and_says_why(cap, caplog):
    # Aggressive growth (every offset qualifies, every 4 steps) on a tiny scene: without a cap the
    # model grows past 0.2 per pixel; with it, it never does, and the log says why, once.
    sc = tiny_scene(n=30, width=24, height=16, n_views=6, backend="torch")
    m = ScaffoldModel(sc.noisy_points(), None, 3.5, ScaffoldConfig(voxel_size=0.1), seed=0)
    st = ScaffoldStrategy(start_stat=1, update_from=4, update_interval=4, update_until=60,
                          grad_threshold=0.0, success_threshold=0.1, update_init_factor=1,
                          update_depth=1, gaussians_per_pixel=cap)  # fmt: skip
    sizes = []
    cfg = TrainConfig(model="scaffold", iters=40, backend="torch", progress=False, export_ply=False,
                      ckpt_every=0)  # fmt: skip
    tr = Trainer(m, sc.views, [], cfg, None, callback=lambda t, s: sizes.append(t.model.n_primitives),
                 strategy=st)  # fmt: skip
    assert tr.train_pixels == 6 * 24 * 16
    with caplog.at_level(logging.INFO, logger="coin_cl.gs.strategy"):
        tr.train()
    sizes.append(tr.model.n_primitives)
    limit = 0.2 * 6 * 24 * 16  # 460.8 -> 46 anchors x 10 offsets
    held = [r for r in caplog.records if "anchor growth held" in r.getMessage()]
    assert sizes[0] == 300
    if cap == 0:
        assert max(sizes) > limit and not held  # what the cap is there to stop
        return
    assert max(sizes) == 460 and all(n <= limit for n in sizes)
    assert len(held) == 1
    assert "cap 460 = 0.2 per training pixel x 2304 pixels" in held[0].getMessage()
    assert tr.log["strategy"]["size_limit"]["neural_gaussians"] == 460
    assert any(e["held_back"] for e in tr.log["refine"])


def test_growth_stops_exactly_at_the_cap_and_keeps_the_steepest():
    # 5 Gaussians qualify (2 small: cloned, 3 large: split), the cap leaves room for 3: the three
    # steepest grow (one clone, two splits), and the model ends at the cap, not past it.
    st = DefaultStrategy(refine_start=0, refine_every=10, reset_every=1000, grow_grad2d=2e-4,
                         grow_scale3d=0.01, prune_opa=0.005, max_gaussians=13)  # fmt: skip
    m = _model()
    st.initialize(m, seed=0)
    small, large = math.log(0.005), math.log(0.05)
    _set(m, "scales", torch.tensor([small] * 5 + [large] * 5)[:, None].repeat(1, 3))
    _set(m, "opacities", inverse_sigmoid(torch.full((10,), 0.5)))
    st.count = torch.full((10,), 1.0)
    st.grad2d = torch.full((10,), 1e-5)
    st.grad2d[[0, 1, 5, 6, 7]] = torch.tensor([3e-3, 1e-3, 5e-3, 4e-3, 2e-3])  # steepest: 5, 6, 0
    ev = st.refine(m, step=9)
    assert ev == {"cloned": 1, "split": 2, "pruned": 0, "reset": 0}
    assert m.n_primitives == 13
    # The clone is Gaussian 0 (the steeper small one); Gaussian 1 stays single.
    means = m.p["means"].data
    assert int((means == means[0]).all(1).sum()) == 2 and int((means == means[1]).all(1).sum()) == 1
    # At the cap nothing grows at all.
    st.count, st.grad2d = torch.full((13,), 1.0), torch.full((13,), 1.0)
    ev = st.refine(m, step=19)
    assert ev["cloned"] == ev["split"] == 0
    assert m.n_primitives == 13
