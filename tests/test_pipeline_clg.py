"""The CLG stage (coin_cl.pipeline.clg) on a small synthetic room, whose ground-truth depth gives P_k
and exact geometry: skipping, resume, compositing, input checks, and guidance lowering the energy and
the masked reprojection residual against the unguided sample of the same seed."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from coin_cl.diffusion import AnalyticFeatures, ScenePriorConfig, opencv_inpaint, train_scene_prior

from coin_cl.pipeline.clg import run_clg, stage_clg
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.reference import reference_points
from coin_cl.scene.io import read_image, to_uint8
from coin_cl.scene.synthetic import make_synthetic


@pytest.fixture(scope="module")
def room():
    s = make_synthetic(n_views=8, width=128, height=96, n_points=2000)
    train = [i for i in range(len(s.cameras)) if not s.is_test[i]]
    # a prior trained for a fixed number of optimizer steps (seconds; deterministic)
    prior = train_scene_prior(
        [s.present[i] for i in train],
        [s.masks[i] for i in train],
        ScenePriorConfig(patch=32, base=16, batch=8, max_steps=30, train_seconds=600.0),
        progress=False,
    )
    k = train[0]
    # I^_k: the consistent truth; I^_n: classical inpaints, inconsistent with it; R_n: the same
    inp = [None] * len(s.cameras)
    for i in train:
        inp[i] = s.absent[i] if i == k else opencv_inpaint(s.present[i], s.masks[i])
    pk = reference_points(s.cameras[k], s.depth_absent[k], s.masks[k])
    return {"s": s, "train": train, "k": k, "prior": prior, "inp": inp, "pk": pk}


def _run(room, out, views=None, masks=None, denoiser=None, guidance_scale=None, **kw):
    s = room["s"]
    # keep_if_worse off: these tests look at what guidance writes; test_keeps_the_input_... turns it on
    cfg = CLGConfig(**({"steps": 4, "progress": False, "keep_if_worse": False} | kw))
    if guidance_scale is not None:
        cfg = replace(cfg, sampler=replace(cfg.sampler, guidance_scale=guidance_scale))
    return run_clg(
        room["k"], room["train"] if views is None else views, s.cameras, room["inp"], room["inp"],
        s.depth_absent, s.masks if masks is None else masks, room["pk"],
        room["prior"] if denoiser is None else denoiser, AnalyticFeatures(), out, cfg,
    )  # fmt: skip


def test_skips_reference_and_empty_mask(room, tmp_path):
    s, k = room["s"], room["k"]
    empty, n = room["train"][1], room["train"][2]
    masks = list(s.masks)
    masks[empty] = np.zeros_like(masks[empty])
    res = _run(room, tmp_path, views=[k, empty, n], masks=masks)
    v = res["views"]
    assert v[f"view_{k:03d}"]["reason"] == "reference view"
    assert v[f"view_{empty:03d}"]["reason"] == "empty mask"
    assert res["n_skipped"] == 2 and res["n_guided"] == 1
    written = sorted(p.name for p in (tmp_path / "images").iterdir())
    assert written == [f"view_{n:03d}.png"]


def test_resume_does_not_redo(room, tmp_path):
    n = room["train"][2]
    res = _run(room, tmp_path, views=[n])
    png = tmp_path / "images" / (f"view_{n:03d}.png")
    before = png.read_bytes()
    assert res["views"][f"view_{n:03d}"]["status"] == "guided"

    class Exploding:
        name = "must not run"
        work_size = room["prior"].work_size

        def make_condition(self, *a, **k):
            raise AssertionError("a written view was redone")

    res2 = _run(room, tmp_path, views=[n], denoiser=Exploding(), guidance_scale=2.0)
    rec = res2["views"][f"view_{n:03d}"]
    assert (
        rec["status"] == "resumed"
        and rec["residual_after"] == res["views"][f"view_{n:03d}"]["residual_after"]
    )
    assert png.read_bytes() == before
    png.unlink()  # without its PNG the view is done again
    with pytest.raises(AssertionError, match="redone"):
        _run(room, tmp_path, views=[n], denoiser=Exploding())


def test_outside_mask_bit_identical(room, tmp_path):
    s = room["s"]
    n = room["train"][3]
    _run(room, tmp_path, views=[n])
    out = to_uint8(read_image(tmp_path / "images" / (f"view_{n:03d}.png")))
    orig = to_uint8(room["inp"][n])
    m = s.masks[n]
    assert np.array_equal(out[~m], orig[~m])
    assert (out[m] != orig[m]).any()  # and it did write something inside


def test_bad_inputs(room, tmp_path):
    s = room["s"]
    n = room["train"][2]
    with pytest.raises(ValueError, match="unknown views"):
        _run(room, tmp_path, views=[99])
    bad = list(room["inp"])
    bad[n] = bad[n].copy()
    bad[n][3, 3, 0] = np.nan
    cfg = CLGConfig(steps=2, progress=False)
    args = (
        s.cameras,
        bad,
        room["inp"],
        s.depth_absent,
        s.masks,
        room["pk"],
        room["prior"],
        AnalyticFeatures(),
    )
    with pytest.raises(ValueError, match="NaN"):
        run_clg(room["k"], [n], *args, tmp_path, cfg)
    bad[n] = room["inp"][n][:-1]
    with pytest.raises(ValueError, match="shape"):
        run_clg(room["k"], [n], *args, tmp_path, cfg)
    with pytest.raises(ValueError, match=r"\[M, 3\]"):
        run_clg(room["k"], [n], s.cameras, room["inp"], room["inp"], s.depth_absent, s.masks,
                room["pk"][:, :2], room["prior"], AnalyticFeatures(), tmp_path, cfg)  # fmt: skip
    with pytest.raises(ValueError, match="reference view"):
        run_clg(99, [n], s.cameras, room["inp"], room["inp"], s.depth_absent, s.masks,
                room["pk"], room["prior"], AnalyticFeatures(), tmp_path, cfg)  # fmt: skip


def test_guidance_lowers_energy_and_residual(room, tmp_path):
    """End to end: same seed, guided (c = 1) against unguided (c = 0), the sampler
    alone (from noise, the sample pasted: what guidance itself does, without the detail band)."""
    views = [i for i in room["train"] if i != room["k"]]
    torch.manual_seed(0)
    alone = {"detail": "none", "strength": 1.0}
    plain = _run(room, tmp_path / "plain", views=views, steps=10, guidance_scale=0.0, **alone)
    guided = _run(room, tmp_path / "guided", views=views, steps=10, guidance_scale=1.0, **alone)
    rows = []
    for stem, g in guided["views"].items():
        p = plain["views"][stem]
        rows.append((p["energy_output"], g["energy_output"], p["residual_after"], g["residual_after"]))
        assert len(g["energies"]) > 0 and p["energies"] == []
    e_p, e_g, r_p, r_g = np.array(rows).T
    print(json.dumps({"energy_unguided": e_p.tolist(), "energy_guided": e_g.tolist(),
                      "residual_unguided": r_p.tolist(), "residual_guided": r_g.tolist()}))  # fmt: skip
    assert len(rows) == 5
    assert e_g.mean() < 0.9 * e_p.mean() and (e_g < e_p).sum() >= 4
    assert r_g.mean() < 0.9 * r_p.mean() and (r_g < r_p).sum() >= 4


def test_stage_clg_reads_the_stage_folders(tmp_path):
    """`stage_clg` on the runner's layout: 1_inpaint/images, 2_refgs/renders + depths (no
    reference_points.ply: P_k comes from the reference depth), writes 3_clg/images."""
    from coin_cl.pipeline.budget import Plan
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
    from coin_cl.pipeline.run_inputs import RunInputs
    from coin_cl.pipeline.runner import StageContext
    from coin_cl.scene import load_scene
    from coin_cl.scene.io import write_png
    from coin_cl.scene.synthetic import write_synthetic

    scene = load_scene(write_synthetic(tmp_path / "scene", n_views=8, width=96, height=72, n_points=1000))
    train = list(scene.train_idx)
    k = train[0]
    inp_dir, gs_dir = tmp_path / "1_inpaint", tmp_path / "2_refgs"
    for i in train:
        stem = scene.cameras[i].name.rsplit(".", 1)[0]
        img = opencv_inpaint(scene.images[i], scene.masks[i])
        write_png(inp_dir / "images" / f"{stem}.png", img)
        write_png(gs_dir / "renders" / f"{stem}.png", img)
        (gs_dir / "depths").mkdir(parents=True, exist_ok=True)
        np.save(gs_dir / "depths" / f"{stem}.npy", scene.extras["depth"][i].astype(np.float32))
    prior = ScenePriorConfig(patch=32, base=16, batch=4, max_steps=3)
    masks = [np.asarray(m, bool) for m in scene.masks]
    masks[train[1]] = np.zeros_like(masks[train[1]])
    counts = {"refgs": 1, "ted_finetune": 0, "ted_adversarial": 0}
    plan = Plan(counts, dict.fromkeys(counts), 600.0, None, "explicit", {})
    expect = sorted(scene.cameras[i].name.rsplit(".", 1)[0] for i in train[2:])
    # without SD2: no sampler where asked (the reference propagated, nothing trained; the pipeline
    # leaves CLG out otherwise); with prior_sampler the scene prior is trained in CLG's own folder
    # and samples
    for name, sampler in (("3_clg", False), ("3_clg_prior", True)):
        clg = CLGConfig(steps=2, progress=False, prior_sampler=sampler, without_sampler=not sampler)
        cfg = CoInConfig(clg=clg, inpaint2d=Inpaint2DConfig(prior=prior))
        run = RunInputs(out=tmp_path, scene=replace(scene, masks=masks), masks=masks, ref=k, cfg=cfg,
                        plan=plan, refgs_cfg=cfg.refgs_settings(k))  # fmt: skip
        ctx = StageContext(name, tmp_path / name, {"1_inpaint": inp_dir, "2_refgs": gs_dir}, {}, run)
        res = stage_clg(ctx)
        written = sorted(p.stem for p in (ctx.out / "images").iterdir())
        assert written == expect and res["n_skipped"] == 2
        assert res["n_guided"] + res["n_kept_input"] == len(expect)
        assert any("P_k" in n for n in ctx.notes) and any("skipped" in n for n in ctx.notes)
        assert not list(inp_dir.glob("scene_prior_*.pt"))  # nothing written into stage 1's folder
        assert bool(list(ctx.out.glob("scene_prior_*.pt"))) == sampler
        assert any("without a sampler" in n for n in ctx.notes) == (not sampler)
        statuses = {r["status"] for r in res["views"].values()} - {"skipped"}
        assert statuses <= ({"guided", "kept input"} if sampler else {"propagated", "kept input"})


def test_a_view_never_leaves_clg_worse_than_it_came(room, tmp_path):
    """With the guard on, each view either passes the checks or keeps I^_n (its PNG is the input)."""
    from coin_cl.scene.io import read_image, to_uint8

    res = _run(room, tmp_path, views=room["train"][1:4], keep_if_worse=True)
    for stem, rec in res["views"].items():
        n = rec["view"]
        written = read_image(tmp_path / "images" / f"{stem}.png")
        if rec["status"] == "kept input":
            assert rec["kept_because"]
            assert np.array_equal(to_uint8(written), to_uint8(room["inp"][n]))
        else:
            assert rec["residual_after"] <= rec["residual_before"]
            assert rec["texture_output"] >= 0.9 * rec["texture_input"]
        # both composites were judged (colour-matched first), and a written one passed
        assert [c["colour_match"] for c in rec["candidates"]] == [True, False]
        if rec["status"] != "kept input":
            assert any(not c["worse"] and c["colour_match"] == rec["colour_match"] for c in rec["candidates"])
    assert res["n_kept_input"] + res["n_guided"] == 3


def test_warp_guard_keeps_the_input_where_the_warped_reference_is_worse(room, tmp_path):
    """Without a sampler (SD2's reference_only mode) the warp of the reference passes the same checks
    when `warp_guard` is on: a reference of hue noise inside its mask is warped into view n when the
    guard is off (an edited reference's path), and view n keeps I^_n when it is on."""
    s, k, n = room["s"], room["k"], room["train"][2]
    inp = list(room["inp"])
    noisy = np.array(inp[k], dtype=np.float32)
    noisy[s.masks[k]] = np.random.default_rng(0).uniform(0, 1, (int(s.masks[k].sum()), 3))
    inp[k] = noisy

    def run(out, guard):
        cfg = CLGConfig(progress=False, sample=False, warp_guard=guard, propagate=False)
        return run_clg(k, [n], s.cameras, inp, inp, s.depth_absent, s.masks, room["pk"], None, None, out, cfg)

    stem = f"view_{n:03d}"
    off, on = run(tmp_path / "off", False)["views"][stem], run(tmp_path / "on", True)["views"][stem]
    assert off["status"] == "warped" and off["support_px"] > 0
    written_off = read_image(tmp_path / "off" / "images" / f"{stem}.png")
    assert not np.array_equal(to_uint8(written_off), to_uint8(inp[n]))
    assert on["status"] == "kept input"
    assert any(w.startswith("colour") for w in on["kept_because"])
    assert np.isfinite(on["lifted_before"]) and np.isfinite(on["lifted_after"])
    written_on = read_image(tmp_path / "on" / "images" / f"{stem}.png")
    assert np.array_equal(to_uint8(written_on), to_uint8(inp[n]))


class _SmoothPosterior:
    """A denoiser whose answer is known: the exact posterior mean of x0 for a Gaussian prior centred
    on the crop's OpenCV Telea fill with per-pixel variance V (tiny): its samples are that smooth fill
    (what a weak model's 64 px sample is: no texture), and x0 depends on z, so guidance has a gradient."""

    name, work_size, prediction_type, V = "smooth posterior", 64, "eps", 1e-4

    def __init__(self):
        from coin_cl.diffusion.sampling import SamplerConfig
        from coin_cl.diffusion.schedule import alphas_cumprod

        self.acp = torch.as_tensor(alphas_cumprod(SamplerConfig().schedule), dtype=torch.float32)

    def make_condition(self, image, hole, prompt=""):
        img, m = image[0].permute(1, 2, 0).numpy(), hole[0, 0].numpy() > 0
        return torch.from_numpy(opencv_inpaint(img, m)).permute(2, 0, 1)[None].float()

    def predict(self, z, t, cond=None):
        a = self.acp[t].view(-1, 1, 1, 1)
        x0 = cond + a.sqrt() * self.V / (a * self.V + 1 - a) * (z - a.sqrt() * cond)
        return (z - a.sqrt() * x0) / (1 - a).sqrt()

    def encode(self, x):
        return x

    def decode(self, z):
        return z


def test_clg_keeps_texture_and_moves_toward_the_reference(tmp_path):
    """On a room whose holes are ~2.8x the 64 px working size (as the shared scene's at
    half resolution), with textured initial inpaints (the exemplar inpainter) and a model whose
    samples are smooth, CLG's images keep the input's texture (within 10%) and come closer to the
    reference (residual lifted with the exact depth, `residual_to_reference`); pasting the
    upsampled sample (detail "none", as the paper pastes it) loses most of the texture."""
    from coin_cl.diffusion.exemplar import exemplar_inpaint

    from coin_cl.metrics import mask_texture
    from coin_cl.pipeline.reprojection import residual_to_reference

    s = make_synthetic(n_views=8, width=512, height=384, n_points=4000)
    train = [i for i in range(len(s.cameras)) if not s.is_test[i]]
    k = train[0]
    inp = [None] * len(s.cameras)
    for i in train:
        inp[i] = s.absent[i] if i == k else exemplar_inpaint(s.present[i], s.masks[i], seed=i)
    pk = reference_points(s.cameras[k], s.depth_absent[k], s.masks[k])
    views = [i for i in train if i != k]

    def run(name, **kw):
        cfg = CLGConfig(steps=10, progress=False, **kw)
        res = run_clg(k, views, s.cameras, inp, inp, s.depth_absent, s.masks, pk, _SmoothPosterior(),
                      AnalyticFeatures(), tmp_path / name, cfg)  # fmt: skip
        out = [None] * len(s.cameras)
        for stem, rec in res["views"].items():
            out[rec["view"]] = read_image(tmp_path / name / "images" / f"{stem}.png")
        tex = np.mean([mask_texture(out[i], s.masks[i]) / mask_texture(inp[i], s.masks[i]) for i in views])
        regions = [s.masks[i] if i in views else None for i in range(len(s.cameras))]
        r = residual_to_reference(s.cameras, s.depth_absent, out, regions, k, s.absent[k], s.masks[k])
        return res, float(tex), r

    regions = [s.masks[i] if i in views else None for i in range(len(s.cameras))]
    r_in = residual_to_reference(s.cameras, s.depth_absent, inp, regions, k, s.absent[k], s.masks[k])
    res, tex, r_out = run("default")
    print(json.dumps({"texture_ratio": tex, "residual_in": r_in, "residual_out": r_out,
                      "kept_input": res["n_kept_input"]}))  # fmt: skip
    assert 0.9 <= tex <= 1.1
    assert r_out < r_in
    assert res["n_guided"] >= 3  # not by keeping the inputs: most views are CLG's own images
    _, tex_none, _ = run("none", detail="none", strength=1.0, keep_if_worse=False)
    assert tex_none < 0.5


def test_propagation_carries_the_reference_in_each_views_own_light(room, tmp_path):
    """One answer, propagated (no sampler, `propagate` on): view n's capture is at another exposure
    than the reference's (x0.8). The reference's truth warped into view n's hole and blended against
    view n's own surroundings lands near view n's truth in its own light; the plain warp keeps the
    reference's brightness, and the initial inpaint (Telea) is further off still."""
    s, k, n = room["s"], room["k"], room["train"][2]
    gain = 0.8
    inp = list(room["inp"])
    inp[n] = (inp[n] * gain).astype(np.float32)
    truth = s.absent[n] * gain
    m = np.asarray(s.masks[n], bool)

    def run(name, **kw):
        cfg = CLGConfig(progress=False, sample=False, **kw)
        res = run_clg(k, [n], s.cameras, inp, inp, s.depth_absent, s.masks, room["pk"], None, None,
                      tmp_path / name, cfg)  # fmt: skip
        rec = res["views"][f"view_{n:03d}"]
        return rec, read_image(tmp_path / name / "images" / f"view_{n:03d}.png")

    rec_h, out_h = run("harmonised")
    rec_w, out_w = run("warped", propagate=False)
    assert rec_h["status"] == "propagated" and rec_w["status"] == "warped"
    from coin_cl.pipeline.reprojection import reference_in_view

    _, weight = reference_in_view(inp[k], s.cameras[n], s.cameras[k], room["pk"], s.depth_absent[k])
    sup = m & (weight > 0)  # where the reference's answer reaches; Telea's fill, scaled, elsewhere
    assert rec_h["support_px"] == rec_w["support_px"] == int(sup.sum()) > 0.2 * m.sum()

    def err(img):
        return float(np.abs(img - truth).mean(-1)[sup].mean())

    def bias(img):  # the exposure left over: mean signed difference
        return float(np.abs((img - truth)[sup].mean(0)).mean())

    e_h, e_w, e_in = err(out_h), err(out_w), err(inp[n])
    print(json.dumps({"harmonised": [e_h, bias(out_h)], "warped": [e_w, bias(out_w)], "input": e_in}))
    assert bias(out_w) > 0.05  # the plain warp carries the reference's exposure
    assert bias(out_h) < 0.25 * bias(out_w)  # the blend takes view n's own
    # at this size the warp's resampling costs about 0.06 at equal exposures: closer than the
    # input and than the plain warp, not exact
    assert e_h < 0.9 * e_w and e_h < 0.9 * e_in
    assert np.array_equal(to_uint8(out_h)[~m], to_uint8(inp[n])[~m])  # outside the mask: untouched
