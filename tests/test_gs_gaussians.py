import numpy as np
import pytest

from coin_cl.gs.gaussians import GaussianConfig, GaussianModel
from coin_cl.gs.model_kinds import scaled_model_config, scaled_strategy
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import TrainConfig, Trainer

BACKEND = "opencl"


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
    tr = Trainer(m, sc.views[1:], sc.views[:1], cfg, strategy=scaled_strategy("3dgs", iters))
    before = tr.evaluate()["psnr"]
    res = tr.train()
    assert res["psnr"] > 22.0 and res["psnr"] > before + 3.0
    assert m.n_primitives > 40  # densification grew the model
