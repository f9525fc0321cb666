import json

import numpy as np
import pytest
import torch

from coin_cl.checkpoint import load_checkpoint
from coin_cl.gs.gaussians import GaussianConfig
from coin_cl.gs.model_kinds import build_model
from coin_cl.gs.strategy import DefaultStrategy, ScaffoldStrategy
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.trainer import (
    CAMERAS_NAME,
    CKPT_NAME,
    LOG_NAME,
    PLY_NAME,
    TrainConfig,
    Trainer,
    TrainingDivergedError,
)

# Both backends are deterministic (the kernels' backward sums gradient shares in a fixed order),
# which "same parameters after resume" needs.
EXACT = "torch"


@pytest.fixture(scope="module")
def scene():
    return tiny_scene(n=30, width=24, height=16, n_views=6, backend=EXACT)


def _model_cfg(kind):
    """Model config and strategy that refine (and, for 3DGS, reset) inside a short run."""
    if kind == "3dgs":
        strategy = DefaultStrategy(refine_start=5, refine_every=8, reset_every=24)
        return GaussianConfig(sh_degree_interval=10), strategy
    # No size cap: these tiny views (1920 pixels) would hold the model at its initial size.
    return None, ScaffoldStrategy(start_stat=2, update_from=8, update_interval=8, update_until=40,
                                  gaussians_per_pixel=0.0)  # fmt: skip


def _trainer(scene, kind, out, iters, callback=None, backend=EXACT, **kw):
    model_cfg, strategy = _model_cfg(kind)
    m = build_model(kind, scene.noisy_points(), None, 3.5, seed=0, model_cfg=model_cfg)
    cfg = TrainConfig(model=kind, iters=iters, backend=backend, progress=False, log_every=5, **kw)
    return Trainer(m, scene.views[1:], scene.views[:1], cfg, out, callback=callback, strategy=strategy)


class Killed(Exception):
    pass


@pytest.mark.parametrize("backend", ["torch", "opencl"])
@pytest.mark.parametrize("kind", ["3dgs", "scaffold"])
def test_checkpoint_kill_resume_matches_uninterrupted(scene, kind, backend, tmp_path):
    iters = 30 if kind == "3dgs" else 24
    kw = dict(backend=backend, export_ply=False)
    ref = _trainer(scene, kind, tmp_path / "ref", iters, ckpt_every=0, **kw)
    ref.train()

    def kill(tr, step):
        if step == 17:  # mid-interval: steps 11..16 are lost and redone after the resume
            raise Killed

    run = _trainer(scene, kind, tmp_path / "run", iters, kill, ckpt_every=10, **kw)
    with pytest.raises(Killed):
        run.train()
    assert not (tmp_path / "run" / (CKPT_NAME + ".tmp")).exists()
    resumed = _trainer(scene, kind, tmp_path / "run", iters, ckpt_every=10, **kw)
    resumed.load_checkpoint()
    assert resumed.step == 10
    resumed.train()
    a, b = ref.model.optimizer.params, resumed.model.optimizer.params
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape, k
        if backend == "opencl":  # bit-reproducible, so bit-equal
            assert torch.equal(a[k], b[k]), k
        else:
            assert torch.allclose(a[k], b[k], atol=1e-5, rtol=1e-5), k
    if kind == "3dgs":  # the run crossed refinements, so row surgery was checkpointed too
        assert any(e["cloned"] + e["split"] + e["pruned"] for e in resumed.log["refine"])


def test_nan_guard_stops_and_keeps_last_good_checkpoint(scene, tmp_path):
    def poison(tr, step):
        if step == 12:
            with torch.no_grad():
                tr.model.optimizer.params["features"][0, 0] = float("nan")

    tr = _trainer(scene, "scaffold", tmp_path, 40, poison, backend="opencl", ckpt_every=5)
    with pytest.raises(TrainingDivergedError, match=r"step 12.*after step 10"):
        tr.train()
    state = load_checkpoint(tmp_path / CKPT_NAME)
    assert state["trainer"]["step"] == 10
    assert all(torch.isfinite(v).all() for v in state["model"]["optimizer"]["params"].values())
    log = json.loads((tmp_path / LOG_NAME).read_text())
    assert log["diverged"]["step"] == 12


@pytest.mark.parametrize("kind", ["3dgs", "scaffold"])
def test_zero_weight_view_leaves_parameters_unchanged(scene, kind):
    tr = _trainer(scene, kind, None, 3, backend="opencl")
    for v in tr.train_views:
        v.weight = 0.0
    before = {k: p.detach().clone() for k, p in tr.model.optimizer.params.items()}
    tr.train_step()
    for k, p in tr.model.optimizer.params.items():
        assert torch.equal(p.detach(), before[k]), k


def test_outputs_written(scene, tmp_path):
    from coin_cl.gs.splats import Splats

    tr = _trainer(scene, "scaffold", tmp_path, 12, backend="opencl", ckpt_every=5, eval_every=6)
    res = tr.train()
    for name in (CKPT_NAME, LOG_NAME, CAMERAS_NAME, PLY_NAME):
        assert (tmp_path / name).is_file(), name
    log = json.loads((tmp_path / LOG_NAME).read_text())
    assert [e["step"] for e in log["eval"]] == [6, 12]
    assert log["train"][-1]["step"] == 12 and "t_fwd" in log["train"][-1]
    assert np.isfinite(res["psnr"])
    g = Splats.from_ply(tmp_path / PLY_NAME)
    assert 0 < len(g) <= tr.model.n_primitives


@pytest.mark.parametrize("kind", ["3dgs", "scaffold"])
def test_checkpoint_from_before_the_strategy_split_still_resumes(scene, kind, tmp_path):
    """Older checkpoints kept the densification statistics and generator in the model (its config
    held the schedule) and the view order in the trainer; they load into the same state."""
    tr = _trainer(scene, kind, tmp_path / "new", 12, backend="opencl", ckpt_every=12, export_ply=False)
    tr.train()
    state = load_checkpoint(tmp_path / "new" / CKPT_NAME)
    st = state.pop("strategy")
    state.pop("terms")
    smp = state.pop("sampler")
    cfg = dict(st["config"])
    if kind == "3dgs":
        state["model"]["cfg"]["densify"] = cfg
    else:
        state["model"]["cfg"].update(cfg)
    state["model"].update(stats=st["stats"], gen=st["gen"])
    state["trainer"].update(gen=smp["gen"], perm=smp["perm"])
    (tmp_path / "old").mkdir()
    torch.save(state, tmp_path / "old" / CKPT_NAME)
    fresh = _model_cfg(kind)[1]
    for k in cfg:  # a different schedule on the caller's side: the checkpoint's wins
        if k.endswith(("every", "interval")):
            setattr(fresh, k, 1000)
    old = _trainer(scene, kind, tmp_path / "old", 12, backend="opencl")
    old.strategy = fresh
    old.load_checkpoint()
    assert old.step == 12 and old.strategy.config() == tr.strategy.config()
    for k, v in st["stats"].items():
        assert torch.equal(getattr(old.strategy, k), v), k
    assert torch.equal(old.strategy.gen.get_state(), tr.strategy.gen.get_state())
    assert old.sampler.state_dict()["perm"] == smp["perm"]
    assert torch.equal(old.sampler.gen.get_state(), tr.sampler.gen.get_state())
    for k, p in old.model.optimizer.params.items():
        assert torch.equal(p, tr.model.optimizer.params[k]), k


def test_checkpoint_by_wall_time_resumes_identically_with_the_same_log(scene, tmp_path):
    """ckpt_seconds checkpoints whatever the step count (here: after every step, ckpt_every off);
    the resumed run equals the uninterrupted one, parameters bit for bit and the loss log too (the
    running means of the interrupted log interval are in the checkpoint)."""
    iters, kw = 24, dict(backend="opencl", export_ply=False, ckpt_every=0)
    ref = _trainer(scene, "scaffold", tmp_path / "ref", iters, ckpt_seconds=0.0, **kw)
    ref.train()

    def kill(tr, step):
        if step == 13:  # mid log interval (log_every=5)
            raise Killed

    run = _trainer(scene, "scaffold", tmp_path / "run", iters, kill, ckpt_seconds=1e-9, **kw)
    with pytest.raises(Killed):
        run.train()
    resumed = _trainer(scene, "scaffold", tmp_path / "run", iters, ckpt_seconds=1e-9, **kw)
    resumed.load_checkpoint()
    assert resumed.step == 13
    resumed.train()
    for k, a in ref.model.optimizer.params.items():
        assert torch.equal(a, resumed.model.optimizer.params[k]), k
    assert resumed.model.cfg == ref.model.cfg  # the config as given (voxel size 0: automatic), not resolved

    def losses(tr):  # timings aside
        return [
            {k: v for k, v in e.items() if "seconds" not in k and not k.startswith("t_")}
            for e in tr.log["train"]
        ]

    assert losses(ref) == losses(resumed) and len(losses(ref)) == iters // 5 + 1
    assert not [p for p in (tmp_path / "run").iterdir() if p.name.startswith(".tmp")]
