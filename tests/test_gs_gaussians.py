import math

import numpy as np
import pytest
import torch

from coin_cl.gs.base import inverse_sigmoid
from coin_cl.gs.gaussians import DensifyConfig, GaussianConfig, GaussianModel
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer, scaled_model_config

BACKEND = "opencl"


def _model(densify: DensifyConfig, n: int = 10) -> GaussianModel:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (n, 3))
    return GaussianModel(pts, None, extent=1.0, cfg=GaussianConfig(densify=densify))


def _set(m: GaussianModel, name: str, value: torch.Tensor) -> None:
    m.optimizer.set_rows(name, value)


def test_densify_counts_on_fixed_inputs():
    d = DensifyConfig(refine_start=0, refine_every=10, reset_every=1000, grow_grad2d=2e-4,
                      grow_scale3d=0.01, prune_opa=0.005)  # fmt: skip
    m = _model(d)
    small, large = math.log(0.005), math.log(0.05)
    _set(m, "scales", torch.tensor([small] * 5 + [large] * 5)[:, None].repeat(1, 3))
    opa = torch.full((10,), 0.5)
    opa[[2, 8]] = 0.001  # below prune_opa, and low gradient: pruned
    _set(m, "opacities", inverse_sigmoid(opa))
    high = torch.zeros(10, dtype=torch.bool)
    high[[0, 1, 5, 6, 7]] = True
    m.count = torch.full((10,), 4.0)
    m.grad2d = torch.where(high, 4 * 1e-3, 4 * 1e-5)  # mean 1e-3 vs 1e-5 against 2e-4
    parent_means = m.p["means"].data[[5, 6, 7]].clone()
    ev = m.refine(step=9)  # the 10th completed step
    assert ev == {"cloned": 2, "split": 3, "pruned": 2, "reset": 0}
    assert m.n_primitives == 10 + 2 + 3 - 2
    for name in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        assert m.p[name].shape[0] == 13
        st = m.optimizer.optims[name].state
        assert all(v["exp_avg"].shape[0] == 13 for v in st.values())
    assert m.grad2d.shape == (13,) and float(m.grad2d.sum()) == 0.0  # statistics restart
    # Split children: scale / 1.6, near their parent (within 4 sigma of the parent's scale).
    children = m.p["means"].data[-6:]
    assert torch.allclose(torch.exp(m.p["scales"].data[-6:]), torch.full((6, 3), 0.05 / 1.6))
    dist = (children[:, None] - parent_means[None]).norm(dim=-1).amin(1)
    assert bool((dist < 4 * 0.05 * math.sqrt(3)).all())


def test_no_refinement_off_schedule_and_opacity_reset():
    d = DensifyConfig(refine_start=50, refine_every=10, reset_every=30, prune_scale3d=0.1)
    m = _model(d)
    m.grad2d = torch.full((10,), 1.0)
    m.count = torch.ones(10)
    assert m.refine(step=19) == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}  # s=20 < start
    ev = m.refine(step=29)  # s = 30: reset only
    assert ev["reset"] == 1 and ev["cloned"] == 0
    assert float(torch.sigmoid(m.p["opacities"].data).max()) <= 0.01 + 1e-6
    # After the first reset, Gaussians larger than prune_scale3d x extent are pruned.
    d2 = DensifyConfig(refine_start=0, refine_every=10, reset_every=30, grow_grad2d=1.0)
    m2 = _model(d2)
    sc = torch.full((10, 3), math.log(0.01))
    sc[[3, 4]] = math.log(0.5)
    _set(m2, "scales", sc)
    assert m2.refine(step=39)["pruned"] == 2  # s = 40 > reset_every


def test_sh_degree_grows():
    m = GaussianModel(np.zeros((3, 3)) + np.arange(3)[:, None], None, 1.0,
                      GaussianConfig(sh_degree=3, sh_degree_interval=100))  # fmt: skip
    assert [m.sh_degree_at(s) for s in (0, 99, 100, 250, 10_000)] == [0, 0, 1, 2, 3]


def test_tiny_scene_trains_3dgs():
    pytest.importorskip("pyopencl")
    sc = tiny_scene(backend=BACKEND)
    iters = 400
    m = GaussianModel(sc.noisy_points(), None, 3.5, scaled_model_config("3dgs", iters), seed=0)
    cfg = TrainConfig(model="3dgs", iters=iters, backend=BACKEND, progress=False, ckpt_every=0,
                      export_ply=False)  # fmt: skip
    tr = Trainer(m, sc.views[1:], sc.views[:1], cfg)
    before = tr.evaluate()["psnr"]
    res = tr.train()
    assert res["psnr"] > 22.0 and res["psnr"] > before + 3.0
    assert m.n_primitives > 40  # densification grew the model
