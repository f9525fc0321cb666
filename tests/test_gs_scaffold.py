import numpy as np
import pytest
import torch

from coin_cl.engine.rendering import rasterize
from coin_cl.gs.model_kinds import scaled_model_config, scaled_strategy
from coin_cl.gs.scaffold import GRID_HALF_CELLS, ScaffoldConfig, ScaffoldModel, min_voxel_size, voxelize
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer

BACKEND = "opencl"


def test_voxelize_merges_points_per_cell():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, -0.1, 0.3], [1.1, 0, 0], [0.9, 0.1, -0.2], [5, 5, 5]])
    v = voxelize(pts, 1.0)
    assert v.shape == (3, 3)
    assert {tuple(r) for r in v.tolist()} == {(0, 0, 0), (1, 0, 0), (5, 5, 5)}


def test_duplicated_points_give_a_voxel_the_anchor_grid_can_hold(caplog):
    """A tiny capture's SfM points can coincide (median nearest-neighbour distance 0, voxel 1e-7 in
    the wild): the automatic voxel is then the grid's floor, logged; an explicit one below it is a
    clear error; every anchor coordinate fits the strategy's hash."""
    rng = np.random.default_rng(0)
    pts = np.concatenate([np.repeat(rng.uniform(-3, 3, (5, 3)), 40, axis=0), [[0.0, 0.0, 0.0]]])
    m = ScaffoldModel(pts, None, 3.0)
    assert np.isfinite(m.voxel_size) and m.voxel_size >= min_voxel_size(pts) > 0
    assert float((m.p["anchors"].abs() / m.voxel_size).max()) < GRID_HALF_CELLS / 16
    pts2 = np.repeat(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + 1e-9]]), 10, axis=0)
    with caplog.at_level("WARNING", logger="coin_cl.gs.scaffold"):
        m2 = ScaffoldModel(pts2, None, 1.0)
    assert "floor" in caplog.text and m2.voxel_size == pytest.approx(min_voxel_size(pts2))
    with pytest.raises(ValueError, match="voxel_size .* too small"):
        ScaffoldModel(pts, None, 3.0, ScaffoldConfig(voxel_size=1e-9))


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
        g = m.decode(cam.center_t, torch.ones(m.n_anchors, dtype=torch.bool))
        full, _, _, meta = rasterize(g["means"], g["quats"], g["scales"], g["opacities"],
                                     g["colors"], cam.viewmat_t, cam.K_t, cam.width, cam.height,
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


def test_fused_decode_equals_masked_decode_values_and_gradients():
    """The fused decode (default: the decode kernel after the MLPs) and Scaffold-GS' boolean-mask
    decode give the same Gaussians (float rounding of exp / sigmoid aside) and the same gradients
    for random cotangents; the selection itself is identical."""
    sc = tiny_scene(backend=BACKEND)
    m = _randomised(np.random.default_rng(2).uniform(-4, 4, (2000, 3)))
    cam = sc.views[0].camera
    vis = m.visible_anchors(cam)
    assert 0 < int(vis.sum()) < m.n_anchors
    keys = ("means", "quats", "scales", "opacities", "colors")
    gen = torch.Generator().manual_seed(3)
    cot = None
    results = {}
    for fused in (False, True):
        m.fused = fused
        m.optimizer.zero_grad()
        g = m.decode(cam.center_t, vis)
        if cot is None:
            cot = {k: torch.randn(g[k].shape, generator=gen) for k in keys}
        sum((g[k] * cot[k]).sum() for k in keys).backward()
        grads = {n: p.grad.clone() for n, p in m.p.items() if p.grad is not None}
        results[fused] = ({k: g[k].detach() for k in (*keys, "selected", "neural_opacity")}, grads)
    (v0, g0), (v1, g1) = results[False], results[True]
    assert int(v0["selected"].sum()) > 0
    for k in ("selected", "neural_opacity"):
        assert torch.equal(v0[k], v1[k]), k
    for k in keys:
        torch.testing.assert_close(v1[k], v0[k], rtol=1e-6, atol=1e-6, msg=k)
    assert set(g0) == set(g1) and {"offsets", "features", "scaling"} <= set(g0)
    for n in g0:  # float32 sums in a different order: relative to each gradient's largest entry
        err = float((g0[n] - g1[n]).abs().max()) / max(float(g0[n].abs().max()), 1e-12)
        assert err < 1e-5, (n, err)


def test_decode_with_no_visible_anchor_or_no_drawn_offset_is_empty_not_an_error():
    m = _randomised(np.random.default_rng(4).uniform(-4, 4, (500, 3)))
    cam = tiny_scene(backend=BACKEND).views[0].camera
    none = torch.zeros(m.n_anchors, dtype=torch.bool)
    for fused in (False, True):
        m.fused = fused
        g = m.decode(cam.center_t, none)
        assert g["means"].shape == (0, 3) and g["colors"].shape == (0, 3) and g["opacities"].shape == (0,)
    # Every offset's opacity negative (last opacity bias -10): nothing selected, empty render.
    with torch.no_grad():
        m.mlps["mlp_opacity"][2].bias.fill_(-10.0)
    for fused in (False, True):
        m.fused = fused
        out = m.render(cam, 0, backend=BACKEND)
        assert int(out.meta["selected"].sum()) == 0 and float(out.image.detach().abs().max()) == 0.0
