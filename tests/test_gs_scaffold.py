import numpy as np
import pytest
import torch

from coin_cl.engine.rendering import rasterize
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel, voxelize
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer, scaled_model_config, scaled_strategy

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


def test_tiny_scene_trains_scaffold():
    pytest.importorskip("pyopencl")
    sc = tiny_scene(backend=BACKEND)
    iters = 300
    m = ScaffoldModel(sc.noisy_points(), None, 3.5, scaled_model_config("scaffold", iters))
    cfg = TrainConfig(model="scaffold", iters=iters, backend=BACKEND, progress=False,
                      ckpt_every=0, export_ply=False)  # fmt: skip
    tr = Trainer(m, sc.views[1:], sc.views[:1], cfg, strategy=scaled_strategy("scaffold", iters))
    before = tr.evaluate()["psnr"]
    res = tr.train()
    assert res["psnr"] > 25.0 and res["psnr"] > before + 5.0
