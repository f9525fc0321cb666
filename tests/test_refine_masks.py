"""3D-first refined masks (coin_cl.pipeline.refine_masks, `coin-cl run --masks refined`) on a small
360-degree capture of the synthetic room, checked against the generator's visibility: the refined
masks stay inside the input masks, are much smaller, and cover the pixels no other view sees."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from coin_cl.diffusion.scene_prior import ScenePriorConfig

from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig, inpaint
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
from coin_cl.pipeline.refine_masks import RefineConfig, read_refined, refine_masks
from coin_cl.pipeline.ted import TEDConfig
from coin_cl.scene import load_scene
from coin_cl.scene.io import read_image
from coin_cl.scene.masks import read_mask
from coin_cl.scene.synthetic import make_synthetic, truly_unseen, write_synthetic

# median abs error of the final render on observed mask pixels (tiny run: 100 Ref-GS steps;
# measured 0.067, the unseen core 0.097)
OBSERVED_TOL = 0.085
# share of the mask the default rule must still call unseen when no view sees behind the object
RIM_BOUND = 0.8


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    syn = make_synthetic(coverage=360, n_views=16, width=96, height=72, n_points=4000, seed=0)
    return syn, load_scene(write_synthetic(tmp_path_factory.mktemp("r360"), syn))


# the precise split of refine_masks' module doc (off by default: end to end it scored lower)
VIEW_CHECK = RefineConfig(view_check=0.05, see_through=0.0, grow_px=0)


def _refine_both(scene, out):
    """The default rule and the view check on one fit (the second run resumes the first's GS)."""
    res = refine_masks(scene, scene.masks, list(scene.train_idx), out / "default", RefineConfig(), iters=300)
    shutil.copytree(out / "default" / "gs", out / "view_check" / "gs")
    refine_masks(scene, scene.masks, list(scene.train_idx), out / "view_check", VIEW_CHECK, iters=300)
    return res


@pytest.fixture(scope="module")
def refined(capture, tmp_path_factory):
    syn, scene = capture
    out = tmp_path_factory.mktemp("refine")
    return out, _refine_both(scene, out)


@pytest.fixture(scope="module")
def refined90(tmp_path_factory):
    syn = make_synthetic(coverage=90, n_views=16, width=96, height=72, n_points=4000, seed=0)
    scene = load_scene(write_synthetic(tmp_path_factory.mktemp("r90"), syn))
    out = tmp_path_factory.mktemp("refine90")
    return syn, scene, out, _refine_both(scene, out)


def _scores(syn, scene, out):
    """(precision, recall) of the unseen core found against the ray-cast truth, and the split's
    share of the masks marked unseen, over the training views."""
    train = list(scene.train_idx)
    _, masks = read_refined(scene, out, train, scene.masks)
    tp = marked = unseen = area = 0
    for i, u in zip(train, truly_unseen(syn, train), strict=True):
        m, r = scene.masks[i], masks[i]
        assert not (r & ~m).any()  # a subset of the input mask
        tp, marked, unseen, area = tp + (r & u).sum(), marked + r.sum(), unseen + u.sum(), area + m.sum()
    return tp / marked, tp / unseen, marked / area


def test_split_finds_the_unseen_core_at_two_coverages(capture, refined, refined90):
    """Measured at these sizes (96x72, 300-step fit), precision / recall of the unseen core: default
    rule 0.47 / 0.94 on the 90-degree arc, 0.58 / 0.84 on the full circle; view check 0.62 / 0.94
    and 0.55 / 0.76 (with the synthetic "SfM" points also taken from the test views: 0.49 / 0.90,
    0.60 / 0.94, 0.64 / 0.88, 0.53 / 0.72; at the demo size, 192x144, 90 degrees, then: default
    0.59 / 0.96, view check 0.72 / 0.92). The truly unseen share is 22 % and 17 %."""
    syn, scene = capture
    syn90, scene90, out90, _ = refined90
    p360, r360, share360 = _scores(syn, scene, refined[0] / "default")
    p90, r90, share90 = _scores(syn90, scene90, out90 / "default")
    vp360, vr360, _ = _scores(syn, scene, refined[0] / "view_check")
    vp90, vr90, _ = _scores(syn90, scene90, out90 / "view_check")
    print(
        f"default: 90 deg {p90:.2f} / {r90:.2f}, 360 deg {p360:.2f} / {r360:.2f}; view check: 90 deg "
        f"{vp90:.2f} / {vr90:.2f}, 360 deg {vp360:.2f} / {vr360:.2f}; observed share {share90:.2f} / "
        f"{share360:.2f}"
    )
    assert p90 > 0.42 and r90 > 0.85, (p90, r90)
    assert p360 > 0.5 and r360 > 0.8, (p360, r360)
    # most of the mask is observed from elsewhere on both
    assert share360 < 0.45 and share90 < 0.55, (share360, share90)
    assert vp90 > 0.55 and vr90 > 0.8, (vp90, vr90)
    assert vp360 > 0.45 and vr360 > 0.6, (vp360, vr360)
    assert vp90 > p90  # the view check's point: fewer observed pixels marked unseen
    res = refined[1]
    _, masks = read_refined(scene, refined[0] / "default", list(scene.train_idx), scene.masks)
    assert res["refined_ratio"] == pytest.approx(
        sum(masks[i].sum() for i in scene.train_idx) / sum(scene.masks[i].sum() for i in scene.train_idx)
    )


def test_split_pngs_cover_train_and_test_views(capture, tmp_path):
    """observed/ and unseen/ partition each input mask, for the training views and for the views
    given as `also` (the test views, judged by the training views only)."""
    syn, scene = capture
    train, tests = list(scene.train_idx)[:6], list(scene.test_idx)[:2]
    refine_masks(scene, scene.masks, train, tmp_path, RefineConfig(), iters=30, also=tests)
    for i in train + tests:
        stem = scene.cameras[i].name.rsplit(".", 1)[0]
        o = read_mask(tmp_path / "observed" / f"{stem}.png")
        u = read_mask(tmp_path / "unseen" / f"{stem}.png")
        assert not (o & u).any() and ((o | u) == scene.masks[i]).all()
    assert not (tmp_path / "masks" / (scene.cameras[tests[0]].name.rsplit(".", 1)[0] + ".png")).exists()


def test_no_view_sees_behind_the_object_gives_the_input_path(capture, tmp_path):
    """Every training view at one pose: nothing behind the object is observed, so the split marks
    the whole mask unseen and the stages downstream get exactly the input-mask path's inputs (the
    captures to 1/255, the input masks), from which they are deterministic."""
    syn, scene = capture
    t0 = scene.train_idx[0]
    same = [scene.cameras[t0] if i in scene.train_idx else c for i, c in enumerate(scene.cameras)]
    same = [replace(c, name=scene.cameras[i].name) for i, c in enumerate(same)]
    imgs = [scene.images[t0] if i in scene.train_idx else im for i, im in enumerate(scene.images)]
    msk = [scene.masks[t0] if i in scene.train_idx else m for i, m in enumerate(scene.masks)]
    one = replace(scene, cameras=same, images=imgs, masks=msk)
    train = list(scene.train_idx)[:4]
    res = refine_masks(one, one.masks, train, tmp_path, VIEW_CHECK, iters=30)
    assert res["refined_ratio"] == 1.0
    images, masks = read_refined(one, tmp_path, train, one.masks)
    for i in train:
        assert (masks[i] == one.masks[i]).all()
        np.testing.assert_allclose(images[i], one.images[i], atol=1 / 255)
    # the default rule judges by coverage and depth alone: from one pose G^rmv keeps the surfaces
    # seen around the object, so it may call a rim of the mask covered; that rim is bounded
    shutil.copytree(tmp_path / "gs", tmp_path / "d" / "gs")
    res = refine_masks(one, one.masks, train, tmp_path / "d", RefineConfig(), iters=30)
    assert res["refined_ratio"] > RIM_BOUND, res["refined_ratio"]


def test_empty_mask_view_keeps_an_empty_split(capture, tmp_path):
    syn, scene = capture
    masks = list(scene.masks)
    e = scene.train_idx[1]
    masks[e] = np.zeros_like(masks[e])
    train = list(scene.train_idx)[:5]
    refine_masks(scene, masks, train, tmp_path, RefineConfig(), iters=20)
    stem = scene.cameras[e].name.rsplit(".", 1)[0]
    assert not read_mask(tmp_path / "unseen" / f"{stem}.png").any()
    assert not read_mask(tmp_path / "observed" / f"{stem}.png").any()


def test_base_images_use_the_render_outside_the_refined_mask(capture, refined):
    syn, scene = capture
    out, _ = refined
    out = out / "default"
    train = list(scene.train_idx)
    images, masks = read_refined(scene, out, train, scene.masks)
    i = train[0]
    m, r = scene.masks[i], masks[i]
    np.testing.assert_allclose(images[i][~m], scene.images[i][~m], atol=1 / 255)  # capture outside
    # inside the input mask but outside the refined one: the object-free render, closer to the
    # room without the object than the capture (which shows the object) is
    band = m & ~r
    gt = syn.absent[[j for j, c in enumerate(syn.cameras) if c.name == scene.cameras[i].name][0]]
    err_render = np.abs(images[i][band] - gt[band]).mean()
    err_capture = np.abs(scene.images[i][band] - gt[band]).mean()
    assert err_render < err_capture


def test_pipeline_with_refined_masks(capture, tmp_path):
    syn, scene = capture
    cfg = CoInConfig(
        inpaint_region="refined", refine=RefineConfig(iters=100), iters_refgs=100, iters_ted_finetune=3,
        iters_ted_adversarial=3, prior_seconds=3,
        inpaint2d=Inpaint2DConfig(prior=ScenePriorConfig(patch=32, base=8, max_steps=4)),
        clg=CLGConfig(steps=2), ted=TEDConfig(n_patches=2), refgs=RefGSConfig(depth_prior_iters=10),
    )  # fmt: skip
    res = inpaint(scene, tmp_path / "run", config=cfg)
    assert res.stages["0_refine"]["status"] == "ran"
    # Ref-GS and CLG share the pipeline's reference (chosen on the input masks), although the refined
    # masks would make Ref-GS's own rule choose another view
    ref = json.loads((tmp_path / "run" / "2_refgs" / "manifest.json").read_text())["settings"]["ref"]
    assert res.stages["2_refgs"]["result"]["reference"]["index"] == ref
    ratio = res.stages["0_refine"]["result"]["refined_ratio"]
    assert 0 < ratio < 1
    assert any("refined masks" in n for n in res.stages["0_refine"]["notes"])
    # stage 1 inpainted only the refined masks: outside them its images are the stage-0_refine images
    i = scene.train_idx[0]
    stem = scene.cameras[i].name.rsplit(".", 1)[0]
    r = read_mask(tmp_path / "run" / "0_refine" / "masks" / f"{stem}.png")
    base = read_image(tmp_path / "run" / "0_refine" / "images" / f"{stem}.png")
    inp = read_image(tmp_path / "run" / "1_inpaint" / "images" / f"{stem}.png")
    assert np.abs(inp[~r] - base[~r]).max() <= 2 / 255
    # A pixel that another view observes ends up, in the final render, close to that observation
    # (the room without the object; Lambertian, so every view sees one colour), closer than the
    # unseen core, which is invented.
    train = list(scene.train_idx)
    err_obs, err_uns = [], []
    for i, u in zip(train, truly_unseen(syn, train), strict=True):
        stem = scene.cameras[i].name.rsplit(".", 1)[0]
        obs = read_mask(tmp_path / "run" / "0_refine" / "observed" / f"{stem}.png") & ~u
        final = read_image(tmp_path / "run" / "eval" / "renders" / f"{stem}.png")
        gt = syn.absent[[j for j, c in enumerate(syn.cameras) if c.name == scene.cameras[i].name][0]]
        err_obs.append(np.abs(final - gt).mean(2)[obs])
        err_uns.append(np.abs(final - gt).mean(2)[u])
    e_obs, e_uns = np.median(np.concatenate(err_obs)), np.median(np.concatenate(err_uns))
    print("median abs error of the final render: observed", e_obs, "unseen", e_uns)
    assert e_obs < OBSERVED_TOL and e_obs < e_uns, (e_obs, e_uns)
    # eval: the split tile and per-part scores, the depth grid and the ghost figure
    metrics = json.loads((tmp_path / "run" / "eval" / "metrics" / "metrics.json").read_text())["mean"]
    assert {"m_psnr_observed", "m_psnr_unseen", "ghost"} <= set(metrics)
    t = scene.test_idx[0]
    stem = scene.cameras[t].name.rsplit(".", 1)[0]
    assert (tmp_path / "run" / "eval" / "metrics" / "grids" / f"depth_{stem}.png").is_file()
    grid = read_image(tmp_path / "run" / "eval" / "metrics" / "grids" / f"{stem}.png")
    assert grid.shape[1] == 6 * scene.cameras[t].width + 10  # five tiles + the split's
    with pytest.raises(ValueError, match="removal"):
        inpaint(scene, tmp_path / "x", config=replace(cfg, prompt="a box", sd_path="/nowhere"))


def test_warp_from_the_captures_observes_more_with_the_captured_colours(capture, refined, tmp_path):
    """`RefineConfig.warp_tol` (off by default, observed_warp's doc): on the same fit, every pixel
    the default split calls observed stays observed, more are added, and in the added pixels
    that the ray-cast truth says are observed the written image (the other view's capture) is far
    closer to the object-free truth than the capture of this view (which shows the object)."""
    syn, scene = capture
    out, _ = refined
    shutil.copytree(out / "default" / "gs", tmp_path / "gs")
    train = list(scene.train_idx)
    refine_masks(scene, scene.masks, train, tmp_path, RefineConfig(warp_tol=0.03), iters=300)
    _, base_masks = read_refined(scene, out / "default", train, scene.masks)
    images, masks = read_refined(scene, tmp_path, train, scene.masks)
    added = err_new = err_cap = 0.0
    for i, u in zip(train, truly_unseen(syn, train), strict=True):
        assert not (masks[i] & ~base_masks[i]).any()  # observed only grows
        new = base_masks[i] & ~masks[i] & ~u
        gt = syn.absent[[j for j, c in enumerate(syn.cameras) if c.name == scene.cameras[i].name][0]]
        added += new.sum()
        err_new += np.abs(images[i][new] - gt[new]).sum()
        err_cap += np.abs(scene.images[i][new] - gt[new]).sum()
    assert added > 0
    assert err_new < 0.5 * err_cap, (err_new / added, err_cap / added)
    with pytest.raises(ValueError, match="warp_tol"):
        RefineConfig(warp_tol=float("nan"))
