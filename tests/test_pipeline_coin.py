"""CoIn end to end (coin_cl.pipeline.coin, `coin-cl run`): every stage once on a tiny synthetic
room, reruns skip what is up to date, a changed setting reruns only the stages it touches, bad
input gives clear errors."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from coin_cl.diffusion.scene_prior import ScenePriorConfig

from coin_cl.cli import main
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig, inpaint
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
from coin_cl.pipeline.runner import OutputFolderError
from coin_cl.pipeline.ted import TEDConfig
from coin_cl.scene import load_scene, write_synthetic

TINY = CoInConfig(
    iters_refgs=12, iters_ted_finetune=3, iters_ted_adversarial=3, prior_seconds=30,
    inpaint2d=Inpaint2DConfig(prior=ScenePriorConfig(patch=32, base=8, max_steps=6)),
    # CLG asked to run without a sampler (the default leaves it out without SD2): the pipeline's CLG path
    clg=CLGConfig(steps=3, without_sampler=True), ted=TEDConfig(n_patches=2),
    refgs=RefGSConfig(depth_prior_iters=10),
    inpaint_region="input",
)  # fmt: skip


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("room"), n_views=8, width=64, height=48, seed=0)


@pytest.fixture(scope="module")
def first_run(room, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    return out, inpaint(room, out, config=TINY)


def test_every_stage_runs_once_and_writes_its_outputs(first_run):
    out, res = first_run
    assert [r["status"] for r in res.stages.values()] == ["ran"] * 6
    assert res.ply.is_file() and (out / "eval" / "metrics" / "metrics.json").is_file()
    assert (out / "eval" / "orbit.gif").is_file()
    assert set(res.metrics) >= {"psnr", "m_psnr", "hf_ratio", "bbox_gmsd"}
    assert np.isfinite(res.metrics["psnr"]) and res.metrics["psnr"] > 8
    assert res.model.n_primitives > 0
    assert len(list((out / "3_clg" / "images").glob("*.png"))) >= 1
    notes = res.stages["1_inpaint"]["notes"]
    assert any("embedded exemplar" in n for n in notes)  # the embedded default is named


def test_rerun_skips_everything(room, first_run):
    out, _ = first_run
    res = inpaint(room, out, config=TINY)
    assert all(r["status"] == "skipped: up to date" for r in res.stages.values())


def test_changed_setting_reruns_that_stage_and_after(room, first_run, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, ted=TEDConfig(n_patches=2, lambda_gen=0.05)))
    status = {k: r["status"] for k, r in res.stages.items()}
    assert status["2_refgs"] == status["3_clg"] == "skipped: up to date"
    assert status["4_ted"] == "ran" and status["eval"] == "ran"


def test_ted_with_zero_iterations_passes_the_refgs_scene_through(room, first_run, tmp_path):
    import shutil

    out = tmp_path / "zero_ted"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, iters_ted_finetune=0, iters_ted_adversarial=0))
    assert res.stages["4_ted"]["status"] == "ran" and res.stages["eval"]["status"] == "ran"
    assert any("passed through" in n for n in res.stages["4_ted"]["notes"])
    assert (out / "4_ted" / "ckpt.pt").is_file() and np.isfinite(res.metrics["psnr"])


def test_ablation_skips_stages_and_says_why(room, tmp_path):
    res = inpaint(room, tmp_path / "abl", config=replace(TINY, skip=("clg", "ted")))
    assert res.stages["3_clg"]["status"].startswith("skipped: asked")
    assert res.stages["4_ted"]["status"].startswith("skipped: asked")
    assert res.stages["eval"]["status"] == "ran"


def test_refgs_trains_around_the_pipeline_reference(room, first_run, tmp_path):
    # Ref-GS used to choose its reference again by its own rule (ignoring --ref, and on refined masks
    # or insertion footprints possibly another view), so P_k came from another view than CLG's camera k.
    from coin_cl.pipeline.reference import choose_reference
    from coin_cl.pipeline.runner import share_stages

    scene = load_scene(room)
    rule = choose_reference(scene)
    other = next(i for i in scene.train_idx if i != rule and scene.masks[i].any())
    for name, skip in (("full", ("clg", "ted")), ("plain", ("refgs", "clg", "ted"))):
        out = tmp_path / name
        share_stages(first_run[0], out, ("0_scene", "1_inpaint"))  # stage 1 does not depend on the reference
        res = inpaint(room, out, config=replace(TINY, ref=other, skip=skip))
        assert res.stages["1_inpaint"]["status"] == "skipped: up to date"
        assert res.stages["2_refgs"]["result"]["reference"]["index"] == other, name


def test_cli_run(room, tmp_path, capsys):
    # seconds of scene-prior training and 3 steps of every training stage: a smoke run
    rc = main(["run", str(room), "--out", str(tmp_path / "cli"), "--mask-kind", "bbox", "--iters", "3",
               "--prior-seconds", "2", "--skip-stage", "clg", "--skip-stage", "ted"])  # fmt: skip
    assert rc == 0
    out = capsys.readouterr().out
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  ") and ln.split()}
    assert rows["2_refgs"].split()[-1] == "ran" and "skipped: asked" in rows["3_clg"]
    assert "m-PSNR" in out and "bbox GMSD" in out  # the metrics as a table (the room has ground truth)
    for what in ("metrics.md", "grids", "orbit.gif", "point_cloud.ply", "plan (explicit)"):
        assert what in out, what


def test_seed_and_clg_settings_reach_their_stages(room, first_run, tmp_path):
    import shutil

    out = tmp_path / "clg"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, clg=CLGConfig(steps=2, without_sampler=True)))
    status = {k: r["status"] for k, r in res.stages.items()}
    assert status["2_refgs"] == "skipped: up to date" and status["3_clg"] == "ran"
    out = tmp_path / "seed"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, seed=1, skip=("clg", "ted")))
    assert res.stages["1_inpaint"]["status"] == "ran" and res.stages["2_refgs"]["status"] == "ran"


def test_force_takes_short_names_and_refuses_typos(room, first_run, tmp_path):
    import shutil

    out = tmp_path / "force"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=TINY, force=("clg",))
    assert res.stages["3_clg"]["status"] == "ran" and res.stages["2_refgs"]["status"] == "skipped: up to date"
    with pytest.raises(ValueError, match="cannot force 'clgg'.*3_clg"):
        inpaint(room, out, config=TINY, force=("clgg",))


def test_same_scene_under_another_spelling_or_resolution_is_accepted(room, first_run, tmp_path):
    import os

    link = tmp_path / "room_link"
    os.symlink(room, link)
    res = inpaint(link, first_run[0], config=TINY)  # a symlink: the same scene, everything up to date
    assert all(r["status"] == "skipped: up to date" for r in res.stages.values())
    half = replace(TINY, resolution=0.5, skip=("clg", "ted"))
    res = inpaint(str(room) + "/", tmp_path / "half", config=half)
    assert res.stages["0_scene"]["status"] == "ran"
    # the half-resolution run may share the folder of the full one: another resolution is not another scene
    import shutil

    out = tmp_path / "both"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, resolution=0.5, skip=("clg", "ted")))
    assert res.stages["0_scene"]["status"] == "ran"


def test_a_smaller_working_size_is_scored_at_the_capture_size_too(room, tmp_path):
    """At half resolution the eval stage renders the test views at the photos' own size as well and
    scores them there (eval/capture): the working-size figure does not see the blur, that one does."""
    from coin_cl.scene.io import read_image

    res = inpaint(room, tmp_path / "half", config=replace(TINY, resolution=0.5, skip=("clg", "ted")))
    full = load_scene(room)
    ev = res.stages["eval"]["result"]
    assert np.isfinite(ev["metrics_capture"]["m_psnr"]) and np.isfinite(ev["metrics"]["m_psnr"])
    for i in full.test_idx:
        stem = Path(full.cameras[i].name).stem
        assert (
            read_image(tmp_path / "half" / "eval" / "capture" / "renders" / f"{stem}.png").shape
            == full.images[i].shape
        )
        assert (
            read_image(tmp_path / "half" / "eval" / "renders" / f"{stem}.png").shape[0]
            == full.images[i].shape[0] // 2
        )
    from coin_cl.pipeline.report import run_report

    assert "photos' own size (eval/capture)" in run_report(res)
    # at the capture's own size nothing else is scored
    assert (
        "metrics_capture"
        not in inpaint(room, tmp_path / "one", config=replace(TINY, skip=("clg", "ted"))).stages["eval"][
            "result"
        ]
    )


def test_default_resolution_is_picked_from_the_image_size(room, tmp_path, caplog):
    with caplog.at_level("INFO", logger="coin_cl.pipeline.coin"):
        inpaint(room, tmp_path / "auto", config=replace(TINY, skip=("clg", "ted")))
    assert "working resolution 1 (64x48 -> 64x48)" in caplog.text


def test_bad_input_is_a_clear_error(room, tmp_path):
    scene = load_scene(room)
    empty = [np.zeros_like(m) for m in scene.masks]
    with pytest.raises(ValueError, match="no training view with a mask"):
        inpaint(scene, tmp_path / "a", masks=empty, config=TINY)
    with pytest.raises(ValueError, match="mask 0 has shape"):
        inpaint(scene, tmp_path / "b", masks=[m[:10] for m in scene.masks], config=TINY)
    with pytest.raises(ValueError, match="view"):
        inpaint(scene, tmp_path / "c", reference="no_such_view.png", config=TINY)
    with pytest.raises(ValueError, match="Stable Diffusion 2"):
        inpaint(scene, tmp_path / "d", prompt="a red apple", config=TINY)
    other = write_synthetic(tmp_path / "other", n_views=8, width=64, height=48, seed=3)
    (tmp_path / "e").mkdir()
    inpaint(room, tmp_path / "e", config=replace(TINY, skip=("clg", "ted")))
    with pytest.raises(OutputFolderError, match="another scene"):
        inpaint(other, tmp_path / "e", config=TINY)
    assert not any((tmp_path / p).exists() for p in ("a/0_scene", "b/0_scene", "d/0_scene"))


def test_render_takes_a_run_folder(first_run, capsys):
    out, res = first_run
    assert main(["render", str(out), "--views", "test"]) == 0
    written = sorted((out / "renders" / "test").glob("*.png"))
    assert len(written) == 2 * len(load_scene(out / "0_scene" / "scene").test_idx)  # image + depth each


def test_auto_region_follows_the_visibility_estimate(room, tmp_path, caplog):
    """ "auto" asks the cheap estimate and says what it found; a wide arc takes refined masks."""
    from coin_cl.gs.carve import build_carve, observed_share
    from coin_cl.pipeline.coin import AUTO_REFINE_SHARE, mask_dilation
    from coin_cl.scene.masks import derive_mask

    scene = load_scene(room)
    train = list(scene.train_idx)
    n = mask_dilation(scene, TINY)  # the estimate sees the training masks, dilated as the run's
    masks = [derive_mask(scene.masks[i], "seg", dilate=n) for i in train]
    share, _ = observed_share(build_carve([scene.cameras[i] for i in train], masks, scene.points))
    with caplog.at_level("INFO", logger="coin_cl.pipeline.coin"):
        res = inpaint(
            room, tmp_path / "auto", config=replace(TINY, inpaint_region="auto", skip=("clg", "ted"))
        )
    want = "refined" if share >= AUTO_REFINE_SHARE else "input"
    assert f"inpaint region: {want} (other views see an estimated {100 * share:.0f}%" in caplog.text
    assert ("0_refine" in res.stages) == (want == "refined")


def test_carve_keeps_the_object_volume_empty_in_the_final_model(room, first_run, tmp_path):
    """With carve=True nothing the densification grows inside the carve volume survives: the final
    model carries the volume and exports no Gaussian inside it (TE-D included)."""
    import shutil

    out = tmp_path / "carve"
    shutil.copytree(first_run[0], out)
    res = inpaint(room, out, config=replace(TINY, carve=True, skip=("clg",)))
    assert res.stages["1_inpaint"]["status"] == "skipped: up to date"  # carving starts at Ref-GS
    assert any("carving the object's volume" in n for n in res.stages["2_refgs"]["notes"])
    vol = res.model.carve
    assert vol is not None and len(vol) > 0
    g = res.model.export_gaussians()
    assert not vol.contains(g.means).any()


def test_the_object_is_removed_not_reconstructed(room, first_run, tmp_path):
    """What a wrong method fails: after 100 Ref-GS steps (+ CLG, TE-D) from the same stage-1
    inpaints, the final renders inside each test view's mask are much closer to the object-absent
    truth than to the capture with the object (measured: 20.5 dB against 15.0-15.5; a method that
    fits the captured pixels in the mask, or keeps the object's Gaussians, is closer to the latter),
    and the metrics CoIn reports are those of its renders."""
    from coin_cl import metrics as M
    from coin_cl.pipeline.runner import share_stages
    from coin_cl.scene.io import read_image

    out = tmp_path / "longer"
    share_stages(first_run[0], out, ("0_scene", "1_inpaint"))
    cfg = replace(TINY, iters_refgs=100, iters_ted_finetune=15, iters_ted_adversarial=15)
    res = inpaint(room, out, config=cfg)
    assert res.stages["1_inpaint"]["status"] == "skipped: up to date"
    scene = load_scene(out / "0_scene" / "scene")
    present = scene.extras["object_present"]
    truth_db = []
    for i in scene.test_idx:
        stem = scene.cameras[i].name.rsplit(".", 1)[0]
        r, gt, m = read_image(out / "eval" / "renders" / f"{stem}.png"), scene.images[i], scene.masks[i]
        to_truth, to_object = M.masked_psnr(r, gt, m), M.masked_psnr(r, present[i], m)
        assert to_truth > to_object + 3.0, (stem, to_truth, to_object)
        truth_db.append(to_truth)
    assert res.metrics["m_psnr"] == pytest.approx(np.mean(truth_db), abs=0.05)


def test_coin_lama_path_reruns_stage_1(room, first_run, tmp_path, monkeypatch):
    """Stage 1's rerun key holds the LaMa file COIN_LAMA_PATH names: setting it, or pointing
    it at another file, reruns 1_inpaint; the same file again is up to date."""
    import shutil

    import torch
    from coin_cl.diffusion.lama import LAMA_ENV

    class Grey(torch.nn.Module):
        def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            return image * (1 - mask) + 0.5 * mask

    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    torch.jit.script(Grey()).save(str(a))
    shutil.copy(a, b)
    out = tmp_path / "lama"
    shutil.copytree(first_run[0], out)
    cfg = replace(TINY, skip=("clg", "ted"))
    status = {}
    for name, env in (("a", a), ("a again", a), ("b", b)):
        monkeypatch.setenv(LAMA_ENV, str(env))
        status[name] = inpaint(room, out, config=cfg).stages["1_inpaint"]["status"]
    assert status == {"a": "ran", "a again": "skipped: up to date", "b": "ran"}


def test_training_masks_are_dilated_unless_declared_exact(room, first_run, tmp_path, caplog):
    """The default dilation is resolved once, logged, and in stage 0's key: none for a scene that
    declares its masks exact (the synthetic room's scene_info.json), the ring of the working size
    for one that does not; an explicit value is kept, a negative one and an unreadable
    scene_info.json are clear errors."""
    import json
    import logging
    import shutil

    from coin_cl.pipeline.coin import mask_dilation
    from coin_cl.scene.masks import auto_dilation

    out, _ = first_run
    scene = load_scene(room)
    assert scene.meta["masks"] == "exact"
    settings = json.loads((out / "0_scene" / "manifest.json").read_text())["settings"]
    assert settings["dilate"] == 0
    with caplog.at_level(logging.INFO, logger="coin_cl.pipeline.coin"):
        assert mask_dilation(scene, CoInConfig()) == 0
    assert "training masks kept as given: the scene declares them exact" in caplog.text
    given = Path(shutil.copytree(room, tmp_path / "given"))
    info = json.loads((given / "scene_info.json").read_text())
    (given / "scene_info.json").write_text(json.dumps({k: v for k, v in info.items() if k != "masks"}))
    plain = load_scene(given)
    cam = plain.cameras[plain.train_idx[0]]
    with caplog.at_level(logging.INFO, logger="coin_cl.pipeline.coin"):
        assert mask_dilation(plain, CoInConfig()) == auto_dilation(cam.width, cam.height) == 1
    assert "training masks dilated by 2 px" in caplog.text
    assert (
        mask_dilation(scene, CoInConfig(mask_dilate=2)) == 2
        and mask_dilation(plain, CoInConfig(mask_dilate=0)) == 0
    )
    (given / "scene_info.json").write_text("[1, 2")
    with pytest.raises(ValueError, match="scene_info.json: not valid JSON"):
        load_scene(given)
    with pytest.raises(ValueError, match="CoInConfig.mask_dilate is -1: give an integer >= 0"):
        inpaint(room, tmp_path / "bad", config=replace(TINY, mask_dilate=-1))


def test_removal_holds_every_mask_to_its_background_depth(first_run):
    """Ref-GS saves D_bg of every training view with a mask and trains with the term;
    TE-D keeps the term (both say so in their notes)."""
    out, res = first_run
    scene = load_scene(out / "0_scene" / "scene")
    with_mask = [i for i in scene.train_idx if np.asarray(scene.masks[i]).any()]
    saved = sorted((out / "2_refgs" / "bg_depths").glob("*.npy"))
    assert len(saved) == len(with_mask) > 0
    d = np.load(saved[0])
    assert d.shape == np.asarray(scene.masks[with_mask[0]]).shape and np.isfinite(d).all() and (d > 0).all()
    assert any("background depth" in n for n in res.stages["2_refgs"]["notes"])
    assert any("keeps the background depth term" in n for n in res.stages["4_ted"]["notes"])


def test_seed_background_puts_anchors_behind_the_object(room, first_run, tmp_path, monkeypatch):
    """`CoInConfig.seed_background` hands Ref-GS seed points on D_bg seen through the reference's
    mask, behind the object (farther than the object's own sparse points there); the default (off)
    hands none. Neither the w/o Ref-GS row (so the naive one) nor an insertion seeds."""
    import coin_cl.pipeline.refgs as refgs_mod
    from coin_cl.gs.background_depth import dilate_mask
    from coin_cl.gs.carve import CarveConfig
    from coin_cl.pipeline.coin import mask_dilation
    from coin_cl.pipeline.reference import choose_reference
    from coin_cl.pipeline.runner import share_stages
    from coin_cl.pipeline.stages import seeds_background
    from coin_cl.scene.masks import derive_mask

    out, res = first_run
    assert not any("seed anchors" in n for n in res.stages["2_refgs"]["notes"])
    got, real = [], refgs_mod.run_refgs

    def spy(*args, **kw):
        got.append(kw["seed_points"])
        return real(*args, **kw)

    monkeypatch.setattr(refgs_mod, "run_refgs", spy)
    on = tmp_path / "on"
    share_stages(out, on, ("0_scene", "1_inpaint"))
    res_on = inpaint(room, on, config=replace(TINY, seed_background=True, skip=("clg", "ted")))
    assert res_on.stages["2_refgs"]["status"] == "ran"  # the setting is in Ref-GS's key
    notes = res_on.stages["2_refgs"]["notes"]
    assert any("behind the object in the reference view seed anchors" in n for n in notes)
    pts, cols = got[0]
    assert len(pts) > 20 and cols.shape == (len(pts), 3) and np.isfinite(pts).all()
    scene = load_scene(out / "0_scene" / "scene")
    k = choose_reference(scene)
    # the reference's training mask as the carve's background depth holds it (grown by its dilate_px)
    mask = derive_mask(scene.masks[k], "seg", dilate=mask_dilation(scene, TINY))
    cam, mask = scene.cameras[k], dilate_mask(mask, CarveConfig().dilate_px)
    px, ok = cam.pixels(pts)
    assert ok.all() and mask[px[:, 1], px[:, 0]].mean() > 0.95  # seen through the reference's mask
    # behind the object: deeper than most sparse points seen through that mask, which are the
    # object's (measured: seeds' median camera z 3.13, the points' 2.33)
    opx, ook = cam.pixels(scene.points)
    seen = ook & mask[opx[:, 1], opx[:, 0]]
    assert np.median(cam.project(pts)[1]) > 1.2 * np.median(cam.project(scene.points[seen])[1])
    on_cfg = replace(TINY, seed_background=True)
    assert not seeds_background(replace(on_cfg, skip=("refgs",)), None)
    assert not seeds_background(on_cfg, np.zeros((4, 4, 3), np.float32))
    assert seeds_background(on_cfg, None) and not seeds_background(TINY, None)


def test_removal_lays_one_learning_rate_schedule_over_ref_gs_and_te_d(first_run):
    """TEDConfig.rates "auto" is "continue" in a removal: Ref-GS's schedules span its own and the
    fine-tune's steps, and TE-D goes on from where Ref-GS stopped."""
    out, _ = first_run
    ted = json.loads((out / "4_ted" / "manifest.json").read_text())["settings"]["cfg"]
    refgs = json.loads((out / "2_refgs" / "manifest.json").read_text())["settings"]
    assert ted["rates"] == "continue"
    assert refgs["schedule_iters"] == TINY.iters_refgs + TINY.iters_ted_finetune


def test_an_explicit_schedule_span_replaces_the_plans_rule(room, first_run, tmp_path):
    """CoInConfig.refgs_schedule_iters: Ref-GS lays its schedules over the span given (how a row
    repeats a default run whose counts were planned again after the span was laid out), and the
    stage's key records it."""
    from coin_cl.pipeline.runner import share_stages

    out = tmp_path / "span"
    share_stages(first_run[0], out, ("0_scene", "1_inpaint"))
    inpaint(room, out, config=replace(TINY, refgs_schedule_iters=40, skip=("clg", "ted")))
    log = json.loads((out / "2_refgs" / "gs" / "log.json").read_text())["refgs"]
    assert log["schedule_iters"] == 40 and log["iters"] == TINY.iters_refgs
    assert json.loads((out / "2_refgs" / "manifest.json").read_text())["settings"]["schedule_iters"] == 40


def test_observed_captures_leaves_the_observed_part_out_of_the_loss(room, tmp_path, monkeypatch):
    """CoInConfig.observed "captures": Ref-GS and TE-D train with the observed part of every refined
    mask (0_refine/observed) left out of view n's loss; "target" leaves nothing out."""
    import coin_cl.pipeline.refgs as refgs_mod
    import coin_cl.pipeline.ted as ted_mod
    from coin_cl.scene.masks import read_mask

    seen: dict[str, list] = {}
    real_refgs, real_ted = refgs_mod.run_refgs, ted_mod.run_ted

    def refgs_spy(*a, **k):
        seen.setdefault("refgs", []).append(k.get("exclude"))
        return real_refgs(*a, **k)

    def ted_spy(model, views, *a, **k):
        seen.setdefault("ted", []).append([None if v.exclude is None else v.exclude.numpy() for v in views])
        return real_ted(model, views, *a, **k)

    monkeypatch.setattr(refgs_mod, "run_refgs", refgs_spy)
    monkeypatch.setattr(ted_mod, "run_ted", ted_spy)
    cfg = replace(TINY, inpaint_region="refined", skip=("clg",))
    assert cfg.observed == "captures"  # the default
    inpaint(room, tmp_path / "target", config=replace(cfg, observed="target"))
    assert seen["refgs"] == [None] and all(e is None for e in seen["ted"][0])
    out = tmp_path / "captures"
    inpaint(room, out, config=replace(cfg, observed="captures"))
    scene = load_scene(room)
    train = list(scene.train_idx)
    ex_refgs, ex_ted = seen["refgs"][1], seen["ted"][1]
    n_out = 0
    for j, i in enumerate(train):
        stem = Path(scene.cameras[i].name).stem
        want = read_mask(out / "0_refine" / "observed" / f"{stem}.png", ex_ted[j].shape)
        assert np.array_equal(ex_refgs[i], want) and np.array_equal(ex_ted[j], want)
        n_out += int(want.sum())
    assert n_out > 0  # the wide arc's masks have an observed part: something was left out
    with pytest.raises(ValueError, match="CoInConfig.observed is .render.: give one of captures, target"):
        inpaint(room, tmp_path / "bad", config=replace(cfg, observed="render"))


@pytest.mark.parametrize(
    ("change", "named"),
    [({"budget_minutes": -1.0}, "--budget"), ({"budget_minutes": float("nan")}, "--budget"),
     ({"prior_seconds": -1.0}, "--prior-seconds"), ({"iters_refgs": 0}, "--iters"),
     ({"resolution": 0.0}, "--resolution")],
)  # fmt: skip
def test_config_refuses_values_the_cli_would_refuse(change, named):
    """The API gets the CLI's checks: CoInConfig's __post_init__, one line naming the flag."""
    with pytest.raises(ValueError, match=named):
        CoInConfig(**change)
    with pytest.raises(ValueError, match="--lama-path"):
        Inpaint2DConfig(lama_path="/nonexistent/big-lama.pt")


def test_a_scene_without_usable_points_names_its_points_file(tmp_path):
    """No sparse points (or NaN ones): refused before any stage, naming the scene's points file
    and `coin-cl prepare`, not a setting the CLI lacks."""
    from coin_cl.pipeline.coin import check_points
    from coin_cl.scene import load_scene, write_synthetic

    root = write_synthetic(tmp_path / "s", n_views=4, width=32, height=24, seed=1)
    (root / "sparse" / "0" / "points3D.bin").write_bytes(bytes(8))  # a model with 0 points
    scene = load_scene(root)
    with pytest.raises(ValueError) as e:
        check_points(scene)
    msg = str(e.value)
    assert "\n" not in msg and str(root / "sparse" / "0" / "points3D.bin") in msg and "coin-cl prepare" in msg
    with pytest.raises(ValueError, match="points3D.bin"):
        inpaint(root, tmp_path / "out", config=CoInConfig(iters_refgs=2))
    assert not (tmp_path / "out").exists()


def _output_hashes(out: Path) -> dict[str, str]:
    """sha256 over the images of stage 1, 3 and the eval renders (names and bytes, sorted)."""
    import hashlib

    res = {}
    for folder in ("1_inpaint/images", "3_clg/images", "eval/renders"):
        h = hashlib.sha256()
        for p in sorted((out / folder).glob("*.png")):
            h.update(p.name.encode() + p.read_bytes())
        res[folder] = h.hexdigest()
    return res


# TINY on the `room` fixture, made on main before the configs moved to `coin_cl.pipeline.config`
# (2 CPU cores, PoCL): the wiring changes left these bits as they were. Compared only where
# COIN_CL_CHECK_HASHES=1 is set: OpenCL devices and torch builds need not agree to the bit.
TINY_HASHES = {
    "1_inpaint/images": "51bc773bb48856dc6d03e6dda33304896aab98ae0004080a0bf96f0d05a67824",
    "3_clg/images": "9cc0163bc6e0c2a8daf77bef47530a8474cb98fdb9c9fbda5f146b4b0c2b7fd0",
    "eval/renders": "b108977d686583d1818abc082aedc12412b22d8fbaf1f65fe1ff4ba10acbc5af",
}


def test_same_settings_give_bit_identical_outputs(room, first_run, tmp_path):
    """With explicit step counts a run is a function of its settings: a second run in a fresh folder
    writes the same bytes (stage 1's inpaints, CLG's guided images, the eval renders), so a change of
    behaviour shows as a changed hash; with COIN_CL_CHECK_HASHES=1, also the same as on main."""
    import os

    again = tmp_path / "again"
    inpaint(room, again, config=TINY)
    first = _output_hashes(first_run[0])
    assert len(list((again / "eval" / "renders").glob("*.png"))) == len(load_scene(room).cameras) == 8
    assert first == _output_hashes(again)
    if os.environ.get("COIN_CL_CHECK_HASHES") == "1":
        assert first == TINY_HASHES


def test_ted_key_leaves_the_run_inputs_as_they_were(room, tmp_path):
    """TE-D's stage key (computed once Ref-GS has run) is the re-planned schedule of
    `schedule.ted_schedule`: computed twice it is the same, and it changes nothing: the run's inputs
    (frozen) and plan hold what they held, and no file is written. Ref-GS's key likewise holds its
    count re-planned from what the stages before it recorded."""
    import copy
    import dataclasses
    import json

    from coin_cl.pipeline.budget import Plan
    from coin_cl.pipeline.coin import coin_stages
    from coin_cl.pipeline.run_inputs import RunInputs
    from coin_cl.pipeline.schedule import stage_schedule, ted_schedule

    scene = load_scene(room)
    # the dilation resolved, as `_run` gives it; TE-D's counts left to the plan
    cfg = replace(TINY, iters_ted_finetune=None, iters_ted_adversarial=None, mask_dilate=0)
    counts = {"refgs": 12, "ted_finetune": 40, "ted_adversarial": 30}
    plan = Plan(counts, {"refgs": 1.0, "ted_finetune": 0.5, "ted_adversarial": 0.8}, 30.0, 0.2, "probe", {})
    masks = [np.asarray(m, bool) for m in scene.masks]
    run = RunInputs(out=tmp_path, scene=scene, masks=masks, ref=scene.train_idx[0], cfg=cfg, plan=plan,
                    refgs_cfg=cfg.refgs_settings(scene.train_idx[0]))  # fmt: skip
    (tmp_path / "2_refgs").mkdir()
    result = {"steps": 12, "train_minutes": 2.0}  # Ref-GS overran its minute: TE-D gets fewer steps
    man = {"key": "k", "settings": {}, "outputs": {}, "result": result, "seconds": 120.0}
    (tmp_path / "2_refgs" / "manifest.json").write_text(json.dumps(man))
    files = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    kept = copy.deepcopy(run)
    ted = next(s for s in coin_stages(run) if s.name == "4_ted")
    first, second = ted.settings(), ted.settings()
    want = ted_schedule(tmp_path, plan, cfg.budget_minutes).steps
    assert first == second and first["iters"] == [want["ted_finetune"], want["ted_adversarial"]]
    assert first["iters"] != [counts["ted_finetune"], counts["ted_adversarial"]]  # not the probe's counts
    refgs = next(s for s in coin_stages(run) if s.name == "2_refgs")
    assert (
        refgs.settings()["iters"]
        == stage_schedule(tmp_path, plan, "2_refgs", cfg.budget_minutes).steps["refgs"]
    )
    assert run.plan == kept.plan and run.cfg == kept.cfg and run.ref == kept.ref
    assert all(np.array_equal(a, b) for a, b in zip(run.masks, kept.masks, strict=True))
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == files
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.plan = replace(plan, steps={})  # type: ignore[misc]
