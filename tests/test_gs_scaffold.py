import math

import numpy as np
import pytest
import torch

from coin_cl.engine.rendering import rasterize
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel, voxelize
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer, scaled_model_config

BACKEND = "opencl"


def test_voxelize_merges_points_per_cell():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, -0.1, 0.3], [1.1, 0, 0], [0.9, 0.1, -0.2], [5, 5, 5]])
    v = voxelize(pts, 1.0)
    assert v.shape == (3, 3)
    assert {tuple(r) for r in v.tolist()} == {(0, 0, 0), (1, 0, 0), (5, 5, 5)}


def test_architecture_matches_scaffold_gs():
    m = ScaffoldModel(np.random.default_rng(0).uniform(-1, 1, (200, 3)), None, 1.0)
    assert m.p["features"].shape[1] == 32 and m.p["offsets"].shape[1:] == (10, 3)
    assert m.p["scaling"].shape[1] == 6
    for name, out, act in (("mlp_opacity", 10, torch.nn.Tanh), ("mlp_cov", 70, None),
                           ("mlp_color", 30, torch.nn.Sigmoid)):  # fmt: skip
        seq = m.mlps[name]
        linears = [x for x in seq if isinstance(x, torch.nn.Linear)]
        assert len(linears) == 2 and linears[0].in_features == 35 and linears[-1].out_features == out
        assert (act is None and not isinstance(seq[-1], torch.nn.Tanh | torch.nn.Sigmoid)) or (
            act is not None and isinstance(seq[-1], act)
        )


def _randomised(points, seed=0) -> ScaffoldModel:
    m = ScaffoldModel(points, None, 1.0, ScaffoldConfig(voxel_size=0.3), seed=seed)
    g = torch.Generator().manual_seed(seed)
    a = m.n_anchors
    m.optimizer.set_rows("features", torch.randn(a, 32, generator=g))
    m.optimizer.set_rows("offsets", torch.randn(a, 10, 3, generator=g))
    m.optimizer.set_rows("scaling", torch.log(torch.full((a, 6), 0.08)))
    return m


def test_frustum_prefilter_culls_but_changes_nothing_visible():
    sc = tiny_scene(backend=BACKEND)
    pts = np.random.default_rng(1).uniform(-8, 8, (3000, 3))
    m = _randomised(pts)
    cam = sc.views[0].camera
    vis = m.visible_anchors(cam)
    assert 0.05 * m.n_anchors < int(vis.sum()) < 0.6 * m.n_anchors  # many culled, many kept
    with torch.no_grad():
        out = m.render(cam, 0, backend=BACKEND)
        g = m.decode(cam.center, torch.ones(m.n_anchors, dtype=torch.bool))
        full, _, _, meta = rasterize(g["means"], g["quats"], g["scales"], g["opacities"],
                                     g["colors"], cam.viewmat, cam.K, cam.width, cam.height,
                                     backend=BACKEND)  # fmt: skip
    assert int(meta["visible"].sum()) > int(out.meta["visible"].sum())  # culled ones were drawable
    # Not bit-equal: the EWA footprint of a splat just outside the frustum can graze the image
    # edge by a fraction of a pixel, and the float-atomic accumulation order differs.
    assert float((out.image - full).abs().max()) < 2e-3
    # Only Gaussians with positive (tanh) opacity are drawn.
    assert out.meta["selected"].sum() == (out.meta["neural_opacity"] > 0).sum()
    assert out.meta["means2d"].shape[0] == int(out.meta["selected"].sum())


def test_anchor_growing_and_pruning_counts():
    cfg = ScaffoldConfig(voxel_size=1.0, update_depth=1, update_init_factor=1,
                         update_interval=100, success_threshold=0.8, grad_threshold=2e-4,
                         min_opacity=0.005)  # fmt: skip
    pts = np.stack([np.arange(20.0), np.zeros(20), np.zeros(20)], 1)
    m = ScaffoldModel(pts, None, 1.0, cfg, seed=0)
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
    m.offset_denom, m.offset_grad_accum = denom.reshape(-1), (grad * denom).reshape(-1)
    m.anchor_denom = torch.full((a,), 100.0)
    m.opacity_accum = torch.full((a,), 50.0)
    m.opacity_accum[[18, 19]] = 0.1  # mean 0.001 < min_opacity: pruned
    ev = m.adjust_anchors()
    assert ev == {"grown": 2, "pruned": 2}
    assert m.n_anchors == 20
    new = m.p["anchors"].data[-2:]
    assert {tuple(r) for r in new.tolist()} == {(3.0, 7.0, 0.0), (4.0, -6.0, 2.0)}
    by_cell = {tuple(r): f for r, f in zip(new.tolist(), m.p["features"].data[-2:], strict=True)}
    assert torch.all(by_cell[(3.0, 7.0, 0.0)] == 1.0) and torch.all(by_cell[(4.0, -6.0, 2.0)] == -2.0)
    assert torch.count_nonzero(m.p["offsets"].data[-2:]) == 0
    assert torch.allclose(m.p["scaling"].data[-2:], torch.zeros(2, 6))  # log(voxel x 1)
    for name in ("offsets", "features", "scaling"):
        st = next(iter(m.optimizer.optims[name].state.values()), None)
        assert m.p[name].shape[0] == 20 and (st is None or st["exp_avg"].shape[0] == 20)
    assert m.offset_denom.shape == (20 * k,) and m.opacity_accum.shape == (20,)
    # The statistics that were used are reset; the rarely-seen slot keeps accumulating.
    assert float(m.offset_denom.view(20, k)[:18, 0].sum()) == 0.0
    assert float(m.offset_denom.view(20, k)[:18, 3].sum()) == 18 * 10.0


def test_scale_regulariser_is_the_mean_volume():
    sc = tiny_scene(backend=BACKEND)
    m = _randomised(sc.noisy_points())
    out = m.render(sc.views[0].camera, 0, backend=BACKEND)
    g = m.decode(sc.views[0].camera.center, m.visible_anchors(sc.views[0].camera))
    expected = 0.01 * float(g["scales"].detach().prod(1).mean())
    assert math.isclose(float(out.reg.detach()), expected, rel_tol=1e-5)


def test_tiny_scene_trains_scaffold():
    pytest.importorskip("pyopencl")
    sc = tiny_scene(backend=BACKEND)
    iters = 300
    m = ScaffoldModel(sc.noisy_points(), None, 3.5, scaled_model_config("scaffold", iters))
    cfg = TrainConfig(model="scaffold", iters=iters, backend=BACKEND, progress=False,
                      ckpt_every=0, export_ply=False)  # fmt: skip
    tr = Trainer(m, sc.views[1:], sc.views[:1], cfg)
    before = tr.evaluate()["psnr"]
    res = tr.train()
    assert res["psnr"] > 25.0 and res["psnr"] > before + 5.0
