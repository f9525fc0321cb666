"""The Ref-GS stage (`coin_cl.pipeline.refgs`) and its trainer plug-ins (`coin_cl.gs.refgs.refgs_terms`):
outputs, bit-exact resume, each ablation switch removing its piece, and the cross-view consistency
the reference brings on the synthetic room with deliberately inconsistent inpaints."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from coin_cl import load_scene
from coin_cl.checkpoint import load_checkpoint
from coin_cl.gs import depth_prior
from coin_cl.gs.anchor_attention import AnchorAttention
from coin_cl.gs.depth_prior import DATASET_DEPTH_PRIOR, GS_DEPTH_PRIOR
from coin_cl.gs.model_kinds import scaled_strategy
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.gs.scaffold import ScaffoldModel
from coin_cl.gs.terms import LossTerm
from coin_cl.gs.trainer import TrainConfig, Trainer
from coin_cl.pipeline import budget as B
from coin_cl.pipeline import reference
from coin_cl.pipeline import refgs as stage
from coin_cl.pipeline.reference import pk_margin_px
from coin_cl.pipeline.refgs import run_refgs
from coin_cl.pipeline.reprojection import residual_to_reference
from coin_cl.scene.ply import read_points_ply
from coin_cl.scene.synthetic import make_synthetic, write_synthetic

W, H = 64, 48


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """(synthetic scene in memory, the loaded scene, per-view inconsistent inpaints).

    Inpaint of view i: the object-absent image, with the mask filled by a solid colour that
    differs per view (the inconsistency Ref-GS must resolve towards the reference)."""
    syn = make_synthetic(n_views=12, width=W, height=H, n_points=3000, supersample=1, seed=0)
    d = write_synthetic(tmp_path_factory.mktemp("room") / "room", syn)
    scene = load_scene(d)
    rng = np.random.default_rng(7)
    targets = []
    for i in range(len(scene.cameras)):
        t = np.asarray(syn.absent[i], np.float32).copy()
        t[np.asarray(scene.masks[i], bool)] = rng.uniform(0.05, 0.95, 3).astype(np.float32)
        targets.append(t)
    return syn, scene, targets


def _gs_depth(syn, scene, k: int) -> np.ndarray:
    """Object-absent depth of view k: stands in for the render of a GS of the unmasked scene."""
    return np.asarray(syn.depth_absent[k], np.float32)


def _cfg(**kw) -> RefGSConfig:
    return RefGSConfig(attn_from=0.0, **kw)  # attention from step 0: short runs exercise it


def test_stage_writes_every_output(room, tmp_path):
    syn, scene, targets = room
    out = tmp_path / "refgs"
    res = run_refgs(scene, targets, out, _cfg(), budget_minutes=None, iters=20, seed=0)
    json.dumps(res)  # JSON-able
    k = res["reference"]["index"]
    assert k == reference.choose_reference(scene)
    assert res["steps"] == 20 and res["n_removed"] > 0
    # No dataset prior in the room: the stage trained its own GS of the captured images.
    assert res["depth_prior"] == GS_DEPTH_PRIOR
    assert json.loads((out / "depth_prior.json").read_text())["name"] == GS_DEPTH_PRIOR
    assert Path(res["checkpoint"]).is_file()
    for i in scene.train_idx:
        stem = Path(scene.cameras[i].name).stem
        assert (out / "renders" / f"{stem}.png").is_file()
        assert np.load(out / "depths" / f"{stem}.npy").shape == (H, W)
        assert np.load(out / "alphas" / f"{stem}.npy").shape == (H, W)
    # P_k: points that project back into the reference's mask + margin, with colours.
    pts, cols = read_points_ply(res["reference_points"])
    assert len(pts) == res["n_reference_points"] > 0 and cols is not None and cols.shape == pts.shape
    cam = scene.cameras[k]
    uv, z = cam.project(pts)
    assert (z > 0).all()
    m = np.asarray(scene.masks[k], bool)
    r = pk_margin_px(m)
    ys, xs = np.nonzero(m)
    px = np.floor(uv).astype(int)
    assert (px[:, 0] >= xs.min() - r - 1).all() and (px[:, 0] <= xs.max() + r + 1).all()
    assert (px[:, 1] >= ys.min() - r - 1).all() and (px[:, 1] <= ys.max() + r + 1).all()
    log = json.loads(Path(res["log"]).read_text())
    assert log["refgs"]["depth_prior"] == GS_DEPTH_PRIOR and log["refgs"]["n_removed"] == res["n_removed"]
    hist = log["view_weights"]["history"]
    assert len(hist) == 20
    kt = log["refgs"]["reference"]["train_index"]
    assert all(h["weight"] == 50.0 for h in hist if h["view"] == kt)
    assert any(h["weight"] not in (50.0, 0.5) for h in hist)  # the sigmoid branch ran
    assert log["refgs"]["attention"]["applied"] > 0
    assert log["refgs"]["terms"]["ref_depth"]["n_applied"] > 0


def test_growth_cap_reaches_the_strategy(room, tmp_path):
    # The cap Ref-GS grows under: per pixel of its training views, as log.json records it.
    syn, scene, targets = room
    cfg = _cfg(feature_attention=False, depth_loss=False, growth_over_initial=1.0)  # the per-pixel cap alone
    res = run_refgs(scene, targets, tmp_path / "c", cfg, budget_minutes=None, iters=12, seed=0,
                    gaussians_per_pixel=0.5)  # fmt: skip
    st = json.loads(Path(res["log"]).read_text())["strategy"]
    pixels = len(scene.train_idx) * W * H
    assert st["gaussians_per_pixel"] == 0.5 and st["train_pixels"] == pixels
    assert st["size_limit"]["neural_gaussians"] == int(0.5 * pixels) // 10 * 10
    assert st["size_limit"]["reason"] == f"cap {int(0.5 * pixels)} = 0.5 per training pixel x {pixels} pixels"
    # a per-pixel cap below the initial model: growth may still reach growth_over_initial x its size
    res = run_refgs(scene, targets, tmp_path / "f", _cfg(feature_attention=False, depth_loss=False),
                    budget_minutes=None, iters=12, seed=0, gaussians_per_pixel=1e-4)  # fmt: skip
    st = json.loads(Path(res["log"]).read_text())["strategy"]
    assert st["min_cap"] > int(1e-4 * pixels) and "min_cap" in st["size_limit"]["reason"]
    assert st["size_limit"]["neural_gaussians"] == st["min_cap"] // 10 * 10


def test_schedule_iters_lay_the_decay_and_growth_over_the_longer_run(room, tmp_path):
    # Ref-GS as the first 12 of 40 steps of one fit: its rates end part-way down, its growth
    # schedule is the 40-step one (TE-D continues both, `TEDConfig.rates`).
    syn, scene, targets = room
    cfg = _cfg(feature_attention=False, depth_loss=False)
    res = run_refgs(scene, targets, tmp_path / "s", cfg, budget_minutes=None, iters=12, seed=0,
                    schedule_iters=40)  # fmt: skip
    log = json.loads(Path(res["log"]).read_text())
    assert log["refgs"]["schedule_iters"] == 40 and res["steps"] == 12
    assert log["strategy"]["update_until"] == scaled_strategy("scaffold", 40).update_until
    saved = _final_state(tmp_path / "s")["model"]["cfg"]
    assert saved["lr_offsets"]["max_steps"] == 40 and saved["lr_mlp_color"]["max_steps"] == 40


def _final_state(out: Path) -> dict:
    return load_checkpoint(out / "gs" / "ckpt.pt")


def test_resume_is_bit_exact(room, tmp_path):
    syn, scene, targets = room
    k = reference.choose_reference(scene)
    kw = dict(budget_minutes=None, iters=24, seed=1, gs_depth=_gs_depth(syn, scene, k), ckpt_every=6)
    run_refgs(scene, targets, tmp_path / "a", _cfg(), **kw)

    class Stop(Exception):
        pass

    def kill(tr, step):
        if step == 15:
            raise Stop

    with pytest.raises(Stop):
        run_refgs(scene, targets, tmp_path / "b", _cfg(), callback=kill, **kw)
    assert _final_state(tmp_path / "b")["trainer"]["step"] == 12
    res = run_refgs(scene, targets, tmp_path / "b", _cfg(), **kw)
    assert res["resumed"] and res["steps"] == 24
    a, b = _final_state(tmp_path / "a"), _final_state(tmp_path / "b")
    pa, pb = a["model"]["optimizer"]["params"], b["model"]["optimizer"]["params"]
    assert pa.keys() == pb.keys()
    for name in pa:
        assert torch.equal(pa[name], pb[name]), name
    assert a["terms"]["photometric"] == b["terms"]["photometric"]  # weights' per-view state, history
    for name, t in a["terms"]["attention"]["attn"].items():
        if isinstance(t, torch.Tensor):
            assert torch.equal(t, b["terms"]["attention"]["attn"][name]), name
    ra = np.load(tmp_path / "a" / "depths" / f"{Path(scene.cameras[k].name).stem}.npy")
    rb = np.load(tmp_path / "b" / "depths" / f"{Path(scene.cameras[k].name).stem}.npy")
    assert np.array_equal(ra, rb, equal_nan=True)


def test_ablation_switches_remove_their_piece(room, tmp_path, monkeypatch):
    syn, scene, targets = room
    k = reference.choose_reference(scene)
    called = {"attn": 0, "depth": 0, "features": 0, "return_depth": 0}

    def no_attn(*a, **kw):
        called["attn"] += 1
        raise AssertionError("attention ran although switched off")

    real_depth = depth_prior.reference_depth_loss

    def count_depth(*a, **kw):
        called["depth"] += 1
        return real_depth(*a, **kw)

    real_render = ScaffoldModel.render

    def spy_render(self, cam, step, **kw):
        called["features"] += kw.get("features") is not None
        called["return_depth"] += bool(kw.get("return_depth")) and bool(kw.get("training"))
        return real_render(self, cam, step, **kw)

    monkeypatch.setattr(AnchorAttention, "forward", no_attn)
    monkeypatch.setattr("coin_cl.gs.depth_prior.reference_depth_loss", count_depth)
    monkeypatch.setattr(ScaffoldModel, "render", spy_render)
    cfg = _cfg(adaptive_weights=False, feature_attention=False, depth_loss=False, prune_points=False,
               bg_depth=False)  # fmt: skip
    res = run_refgs(scene, targets, tmp_path / "off", cfg, budget_minutes=None, iters=12, seed=0)
    log = json.loads(Path(res["log"]).read_text())
    assert all(h["weight"] == 1.0 for h in log["view_weights"]["history"])  # reference included
    assert called == {"attn": 0, "depth": 0, "features": 0, "return_depth": 0}
    assert set(log["terms"]) == {"photometric", "scale_reg"}
    assert res["n_removed"] == 0 and res["depth_prior"] is None
    assert not (tmp_path / "off" / "depth_prior.npy").exists()
    assert not (tmp_path / "off" / "bg_depths").exists()
    # The same run with the pieces on calls each of them (so the zero counts above mean something).
    monkeypatch.undo()
    monkeypatch.setattr("coin_cl.gs.depth_prior.reference_depth_loss", count_depth)
    monkeypatch.setattr(ScaffoldModel, "render", spy_render)
    res = run_refgs(scene, targets, tmp_path / "on", _cfg(), budget_minutes=None, iters=12, seed=0,
                    gs_depth=_gs_depth(syn, scene, k))  # fmt: skip
    log = json.loads(Path(res["log"]).read_text())
    # Depth is rendered on the reference (ref_depth) and on every view with a mask (bg_depth).
    assert called["depth"] > 0 and called["features"] > 0 and called["return_depth"] == 12
    assert set(log["terms"]) == {"photometric", "scale_reg", "ref_depth", "bg_depth", "attention"}
    assert log["refgs"]["terms"]["bg_depth"]["n_applied"] > 0
    assert res["n_removed"] > 0


def test_dataset_prior_wins_and_is_fitted_as_disparity(room, tmp_path):
    syn, scene, targets = room
    k = reference.choose_reference(scene)
    disp = 1.0 / np.asarray(syn.depth_absent[k], np.float32)
    scene2 = dataclasses.replace(scene, priors={"depth": {k: disp}})
    res = run_refgs(scene2, targets, tmp_path / "d", _cfg(feature_attention=False), budget_minutes=None,
                    iters=8, gs_depth=np.ones((H, W), np.float32))  # fmt: skip
    assert res["depth_prior"] == DATASET_DEPTH_PRIOR
    log = json.loads(Path(res["log"]).read_text())
    fit = log["refgs"]["terms"]["ref_depth"]["last_fit"]
    assert fit["A"] > 0  # disparity of the render vs the prior's disparity: same direction


def test_a_minute_budget_follows_the_pipelines_rule(room, tmp_path, monkeypatch):
    """`budget_minutes` becomes steps by `budget.standalone_steps` at the probe's rate (here a fixed
    1.0 s/step), and a rerun keeps the first call's plan without probing again."""
    syn, scene, targets = room
    calls = []
    monkeypatch.setattr(stage, "probe_seconds_per_step", lambda *a: calls.append(a) or 1.0)
    minutes = 6 * B.STEP_COST["refgs"] / 60.0  # 6 Ref-GS steps at 1.0 s per probe step
    res = run_refgs(scene, targets, tmp_path / "b", _cfg(feature_attention=False, depth_loss=False),
                    budget_minutes=minutes, iters=None, seed=0)  # fmt: skip
    assert res["iters"] == B.stage_steps("refgs", minutes, 1.0) == 6 and len(calls) == 1
    res = run_refgs(scene, targets, tmp_path / "b", _cfg(feature_attention=False, depth_loss=False),
                    budget_minutes=2 * minutes, iters=None, seed=0)  # fmt: skip
    assert res["iters"] == 6 and len(calls) == 1


def test_the_count_is_planned_again_from_the_first_steps_and_kept_on_a_rerun(room, tmp_path, monkeypatch):
    """`replan_seconds`: PROBE_STEPS steps of a thrown-away copy time the machine (here each reported
    as 0.03 s), the count follows `budget.refgs_steps_from_rate` and stage.json records it; the copy
    leaves no trace (the run equals one given that count outright), and a rerun with the same request
    keeps the decision without timing again."""
    syn, scene, targets = room
    calls = []

    def timed(step, steps, warmup):
        for _ in range(steps + warmup):
            step()
        calls.append(steps)
        return 0.03

    monkeypatch.setattr(stage, "median_step_seconds", timed)
    # a floor of 10 steps instead of 100: the count then comes from the rate (tens of steps), and the
    # three runs below train those instead of the real floor's 300 steps
    monkeypatch.setitem(B.costs.MIN_STEPS, "refgs", 10)
    # the stage's clock stands still: the seconds left after its setup are the 1.5 asked, on any
    # machine (a loaded CI machine took longer than that to set up, leaving none)
    monkeypatch.setattr(stage, "time", SimpleNamespace(perf_counter=lambda: 0.0))
    cfg = _cfg(feature_attention=False, depth_loss=False)
    res = run_refgs(scene, targets, tmp_path / "r", cfg, budget_minutes=None, iters=7, seed=0,
                    replan_seconds=1.5, schedule_iters=27)  # fmt: skip
    rp = res["replan"]
    assert calls == [B.PROBE_STEPS] and rp["request"] == 7 and rp["first_seconds_per_step"] == 0.03
    assert rp["seconds"] == 1.5
    assert rp["steps"] == B.refgs_steps_from_rate(rp["seconds"], 0.03, rp["size"], rp["size_limit"])[0]
    assert res["iters"] == res["steps"] == rp["steps"] > B.costs.MIN_STEPS["refgs"]  # the rate decided
    assert json.loads((tmp_path / "r" / stage.STAGE_JSON).read_text())["replan"] == rp
    log = json.loads(Path(res["log"]).read_text())["refgs"]
    assert log["schedule_iters"] == rp["steps"] + 20  # TE-D's 20 steps still follow it
    direct = run_refgs(scene, targets, tmp_path / "d", cfg, budget_minutes=None, iters=rp["steps"], seed=0,
                       schedule_iters=rp["steps"] + 20)  # fmt: skip
    assert direct["replan"] is None
    pa = _final_state(tmp_path / "r")["model"]["optimizer"]["params"]
    pb = _final_state(tmp_path / "d")["model"]["optimizer"]["params"]
    for name in pa:
        assert torch.equal(pa[name], pb[name]), name
    again = run_refgs(scene, targets, tmp_path / "r", cfg, budget_minutes=None, iters=7, seed=0,
                      replan_seconds=1.5, schedule_iters=27)  # fmt: skip
    assert calls == [B.PROBE_STEPS] and again["iters"] == rp["steps"] and again["replan"] == rp
    # a record that does not hold together (its steps are not the stage's count) is not trusted
    planted = tmp_path / "p"
    planted.mkdir()
    (planted / stage.STAGE_JSON).write_text(json.dumps({"iters": 5, "replan": {**rp, "steps": 10**9}}))
    res = run_refgs(scene, targets, planted, cfg, budget_minutes=None, iters=7, seed=0,
                    replan_seconds=1.5, schedule_iters=27)  # fmt: skip
    assert len(calls) == 2 and res["iters"] == res["replan"]["steps"] < 10**9


def test_render_kwargs_clash_is_an_error():
    from coin_cl.gs.synthetic import tiny_scene
    from coin_cl.gs.terms import PhotometricLoss

    sc = tiny_scene(n=20, width=16, height=12, n_views=3)

    class Depth(LossTerm):
        name = "a"

        def before_render(self, view, index, step, model):
            return {"return_depth": True}

        def __call__(self, ctx):
            assert ctx.out.depth is not None
            return ctx.out.image.new_zeros(())

    model = ScaffoldModel(sc.noisy_points(), None, 3.0)
    cfg = TrainConfig(iters=1, backend="torch", progress=False, export_ply=False)
    Trainer(model, sc.views, [], cfg, terms=[PhotometricLoss(), Depth()]).train()  # depth delivered
    d2 = Depth()
    d2.name = "b"  # two terms asking for the same flag agree: accepted
    Trainer(model, sc.views, [], cfg, terms=[PhotometricLoss(), Depth(), d2]).train()

    class NoDepth(Depth):
        name = "c"

        def before_render(self, view, index, step, model):
            return {"return_depth": False}

    tr = Trainer(model, sc.views, [], cfg, terms=[PhotometricLoss(), Depth(), NoDepth()])
    with pytest.raises(ValueError, match="already set"):
        tr.train()


def test_scaffold_features_override():
    from coin_cl.gs.synthetic import tiny_scene

    sc = tiny_scene(n=20, width=16, height=12, n_views=2)
    model = ScaffoldModel(sc.noisy_points(), None, 3.0)
    with torch.no_grad():
        model.p["features"].normal_(generator=torch.Generator().manual_seed(0))
    cam = sc.views[0].camera
    base = model.render(cam, 0, backend="torch").image
    same = model.render(cam, 0, backend="torch", features=model.p["features"].clone()).image
    assert torch.equal(base, same)
    other = model.render(cam, 0, backend="torch", features=torch.zeros_like(model.p["features"])).image
    assert not torch.equal(base, other)
    with pytest.raises(ValueError, match="override"):
        model.render(cam, 0, backend="torch", features=torch.zeros(3, 32))


def reference_residual(syn, scene, targets, out: Path, k: int) -> float:
    """Mean |R_n(p) - T_k(warp_k(p))| over mask pixels p of the non-reference training views
    whose object-absent surface point lands inside the reference's mask (true depth, true poses):
    how far the renders are from the reference's content in the hole."""
    from imageio.v2 import imread

    n = len(scene.cameras)
    images, regions = [None] * n, [None] * n
    for i in scene.train_idx:
        if i != k:
            stem = Path(scene.cameras[i].name).stem
            images[i] = imread(out / "renders" / f"{stem}.png").astype(np.float32) / 255
            regions[i] = np.asarray(scene.masks[i], bool)
    depths = [np.asarray(d) for d in syn.depth_absent]
    return residual_to_reference(scene.cameras, depths, images, regions, k, targets[k], scene.masks[k])


def _residuals(syn, scene, targets, tmp_path, *cfgs: RefGSConfig, iters: int = 300) -> list[float]:
    """Masked residuals to the reference after `iters` steps, seed 0: plain training's, then each of
    `cfgs`' (plain trained once: the same inputs and seed give the same model)."""
    k = reference.choose_reference(scene)
    kw = dict(budget_minutes=None, iters=iters, seed=0, gs_depth=_gs_depth(syn, scene, k))
    plain = RefGSConfig(adaptive_weights=False, feature_attention=False, depth_loss=False, prune_points=False,
                        bg_depth=False)  # fmt: skip
    errors = []
    for i, cfg in enumerate((plain, *cfgs)):
        run_refgs(scene, targets, tmp_path / str(i), cfg, **kw)
        errors.append(reference_residual(syn, scene, targets, tmp_path / str(i), k))
    return errors


@pytest.mark.slow
def test_refgs_pulls_views_towards_the_reference(room, tmp_path):
    """Every non-reference view has a different solid colour in its mask, the
    reference a plausible fill (the true background, as a good inpaint would be). The paper's Ref-GS
    (weights, pruning, reference depth, attention from mid-run; the background depth term
    off) ends closer to the reference's content in the other views' masks than plain training.
    Measured at 300 steps: plain 0.1329, Ref-GS 0.1240; with the background depth term (the default)
    0.1263: holding every mask at its background depth leaves the views' conflicting colours fewer
    places to go than the reference. (Plain 0.1375, Ref-GS 0.1161, default 0.1257 while the synthetic
    "SfM" points also came from the test views: points behind the object that no training view sees
    gave plain training the truth there. The pull is smaller on the honest scene, so are the margins.)"""
    syn, scene, targets = room
    k = reference.choose_reference(scene)
    targets = list(targets)
    targets[k] = np.asarray(syn.absent[k], np.float32)
    e_plain, e_ref, e_default = _residuals(syn, scene, targets, tmp_path, RefGSConfig(bg_depth=False),
                                           RefGSConfig())  # fmt: skip
    print(f"residual to the reference: plain {e_plain:.4f}, Ref-GS {e_ref:.4f}, default {e_default:.4f}")
    assert e_ref < 0.96 * e_plain
    assert e_default < 0.98 * e_plain


@pytest.mark.slow
def test_adaptive_weights_pull_towards_an_arbitrary_reference(room, tmp_path):
    """Every view, the reference too, has its own solid colour in the mask. The adaptive weights
    alone pull the other views to the reference's colour (measured: plain 0.2947, weights 0.1342).
    Full Ref-GS does not here (0.3888): anchor attention replaces in-mask features with convex
    combinations of the ring's, i.e. the surroundings, which an arbitrary colour is not."""
    syn, scene, targets = room
    off = dict(feature_attention=False, depth_loss=False, prune_points=False, bg_depth=False)
    e_plain, e_w = _residuals(syn, scene, targets, tmp_path, RefGSConfig(**off))
    print(f"masked residual to the reference: plain {e_plain:.4f}, adaptive weights {e_w:.4f}")
    assert e_w < 0.6 * e_plain
