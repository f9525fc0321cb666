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
from coin_cl.pipeline.refine_masks import RefineConfig, read_refined, refine_masks, vote_ring
from coin_cl.pipeline.ted import TEDConfig
from coin_cl.scene import load_scene
from coin_cl.scene.io import read_image
from coin_cl.scene.masks import derive_mask, dilate_mask, read_mask
from coin_cl.scene.synthetic import make_synthetic, truly_unseen, write_synthetic

# median abs error of the final render on observed mask pixels (tiny run: 100 Ref-GS steps;
# measured 0.067, the unseen core 0.097)
OBSERVED_TOL = 0.085
# share of the mask the default rule must still call unseen when no view sees behind the object
RIM_BOUND = 0.8
# the strict removal vote against the majority vote on one fit (test_strict_vote_...): precision of
# the unseen core it must gain, recall it may lose (measured below at these sizes)
STRICT_GAIN = 0.1
RECALL_COST = 0.12
# exact masks: the vote on the default ring against the vote on the masks alone (test_tight_...)
# The vote on the ring at 96x72, 90 degrees, against the tight vote (precision / recall): 0.56 / 0.80
# -> 0.66 / 0.84 on an AMD EPYC Zen 3, 0.60 / 0.79 -> 0.67 / 0.78 on a Xeon (Intel's runtime rounds
# the fit differently per CPU): precision and F1 gain on both, recall moves either way by a little.
RING_PRECISION_GAIN = 0.05
RING_F1_GAIN = 0.02
RING_RECALL_LOSS = 0.03  # the most recall the ring may cost


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    syn = make_synthetic(coverage=360, n_views=16, width=96, height=72, n_points=4000, seed=0)
    return syn, load_scene(write_synthetic(tmp_path_factory.mktemp("r360"), syn))


# the precise split of refine_masks' module doc (off by default: end to end it scored lower)
VIEW_CHECK = RefineConfig(view_check=0.05, see_through=0.0, grow_px=0)
# a looser split, for comparison: a majority removal vote and a one-pixel growth
MAJORITY = RefineConfig(min_fraction=0.5, grow_px=1)


def _dilated(scene) -> list[np.ndarray]:
    """The training masks as the pipeline hands them to the split: dilated (`CoInConfig.mask_dilate`
    auto: one 5x5 step at these sizes), so that they cover the object's fringe in every view."""
    return [derive_mask(m, "seg", dilate=1) if i in scene.train_idx and m.any() else m
            for i, m in enumerate(scene.masks)]  # fmt: skip


def _refine_both(scene, out):
    """The default rule, the view check and the majority vote on one fit (later runs resume the
    first's GS), on the pipeline's dilated masks."""
    masks = _dilated(scene)
    res = refine_masks(scene, masks, list(scene.train_idx), out / "default", RefineConfig(), iters=300)
    for name, cfg in (("view_check", VIEW_CHECK), ("majority", MAJORITY)):
        shutil.copytree(out / "default" / "gs", out / name / "gs")
        refine_masks(scene, masks, list(scene.train_idx), out / name, cfg, iters=300)
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
    share of the masks marked unseen, over the training views (inside the object's own masks; the
    dilation's ring is left out of the count)."""
    train = list(scene.train_idx)
    given = _dilated(scene)
    _, masks = read_refined(scene, out, train, given)
    tp = marked = unseen = area = 0
    for i, u in zip(train, truly_unseen(syn, train), strict=True):
        assert not (masks[i] & ~given[i]).any()  # a subset of the input mask
        m, r = scene.masks[i], masks[i] & scene.masks[i]
        tp, marked, unseen, area = tp + (r & u).sum(), marked + r.sum(), unseen + u.sum(), area + m.sum()
    return tp / marked, tp / unseen, marked / area


def test_split_finds_the_unseen_core_at_two_coverages(capture, refined, refined90):
    """Measured at these sizes (96x72, 300-step fit, the pipeline's dilated masks), precision /
    recall of the unseen core: default rule (strict vote, no growth) 0.63 / 0.94 on the 90-degree
    arc, 0.70 / 0.91 on the full circle; view check 0.54 / 0.96 and 0.49 / 0.87; the majority vote
    with a one-pixel growth (the default before) 0.47 / 0.94 and 0.43 / 0.99. At the demo size,
    192x144, 90 degrees: default 0.75 / 0.94, the majority vote 0.46 / 0.96
    (`benchmarks/refine_split.py`). The truly unseen share is 22 % and 17 %."""
    syn, scene = capture
    syn90, scene90, out90, _ = refined90
    p360, r360, share360 = _scores(syn, scene, refined[0] / "default")
    p90, r90, share90 = _scores(syn90, scene90, out90 / "default")
    vp360, vr360, _ = _scores(syn, scene, refined[0] / "view_check")
    vp90, vr90, _ = _scores(syn90, scene90, out90 / "view_check")
    print(
        f"default: 90 deg {p90:.2f} / {r90:.2f}, 360 deg {p360:.2f} / {r360:.2f}; view check: 90 deg "
        f"{vp90:.2f} / {vr90:.2f}, 360 deg {vp360:.2f} / {vr360:.2f}; unseen share {share90:.2f} / "
        f"{share360:.2f}"
    )
    assert p90 > 0.55 and r90 > 0.85, (p90, r90)
    assert p360 > 0.6 and r360 > 0.8, (p360, r360)
    # most of the mask is observed from elsewhere on both
    assert share360 < 0.35 and share90 < 0.45, (share360, share90)
    assert vp90 > 0.45 and vr90 > 0.85, (vp90, vr90)
    assert vp360 > 0.4 and vr360 > 0.75, (vp360, vr360)
    res = refined[1]
    given = _dilated(scene)
    _, masks = read_refined(scene, refined[0] / "default", list(scene.train_idx), given)
    assert res["refined_ratio"] == pytest.approx(
        sum(masks[i].sum() for i in scene.train_idx) / sum(given[i].sum() for i in scene.train_idx)
    )


def test_strict_vote_keeps_the_background_behind_the_object(capture, refined, refined90):
    """The removal vote (module doc, step 2): background just behind the object lies inside the
    masks of most views, so a majority vote deletes surface that some view sees, and the split
    marks it unseen. On the same fit the strict default marks far fewer exactly observed pixels
    unseen (precision of the unseen core) and keeps most of the recall on both arcs; a vote that
    removed background instead of the object would fail the first, one that kept the object the
    second."""
    syn, scene = capture
    syn90, scene90, out90, _ = refined90
    for s, sc, out in ((syn, scene, refined[0]), (syn90, scene90, out90)):
        p, r, _ = _scores(s, sc, out / "default")
        mp, mr, _ = _scores(s, sc, out / "majority")
        print(f"strict vote {p:.3f} / {r:.3f}, majority {mp:.3f} / {mr:.3f}")
        assert p > mp + STRICT_GAIN, (p, mp)
        assert r > mr - RECALL_COST, (r, mr)


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
    given = _dilated(scene)
    images, masks = read_refined(scene, out, train, given)
    i = train[0]
    m, r = given[i], masks[i]
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
    given = _dilated(scene)
    refine_masks(scene, given, train, tmp_path, RefineConfig(warp_tol=0.03), iters=300)
    _, base_masks = read_refined(scene, out / "default", train, given)
    images, masks = read_refined(scene, tmp_path, train, given)
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


def test_vote_ring_makes_up_the_default_ring():
    """The vote's extra dilation (iterations of 2 px): what the training masks lack of the default
    ring, never negative."""
    assert vote_ring(192, 144, 0) == 1 and vote_ring(192, 144, 1) == 0
    assert vote_ring(504, 284, 0) == 4 and vote_ring(504, 284, 2) == 2 and vote_ring(504, 284, 6) == 0


def test_tight_masks_vote_on_the_default_ring(refined90, tmp_path):
    """Exact masks (`--mask-dilate 0`): the unanimous vote on them alone keeps Gaussians of the
    object's silhouette that some view has just outside its mask; they cover the footprint and the
    split takes it for observed. The vote on the masks widened by `vote_ring`, on the same fit and
    the same (tight) split region, gains precision and F1 at about the same recall (figures by
    `RING_PRECISION_GAIN`); a vote that ignored the wider masks would gain neither."""
    syn, scene, out90, _ = refined90
    train = list(scene.train_idx)
    tight = [np.asarray(m, bool) for m in scene.masks]
    cam = scene.cameras[train[0]]
    ring = vote_ring(cam.width, cam.height, 0)
    wide = [dilate_mask(m, iterations=ring) if i in train and m.any() else m for i, m in enumerate(tight)]
    for name, vote in (("tight", None), ("ring", wide)):
        shutil.copytree(out90 / "default" / "gs", tmp_path / name / "gs")
        refine_masks(scene, tight, train, tmp_path / name, RefineConfig(), iters=300, vote_masks=vote)
    p_t, r_t, _ = _scores(syn, scene, tmp_path / "tight")
    p_r, r_r, _ = _scores(syn, scene, tmp_path / "ring")
    print(f"tight vote {p_t:.3f} / {r_t:.3f}, vote on the ring {p_r:.3f} / {r_r:.3f}")
    f1_t, f1_r = 2 * p_t * r_t / (p_t + r_t), 2 * p_r * r_r / (p_r + r_r)
    assert p_r > p_t + RING_PRECISION_GAIN, (p_r, p_t)
    assert f1_r > f1_t + RING_F1_GAIN, (f1_r, f1_t)
    assert r_r > r_t - RING_RECALL_LOSS, (r_r, r_t)


def test_small_observed_islands_go_back_to_the_unseen_core():
    from coin_cl.pipeline.refine_masks import fill_islands

    mask = np.zeros((40, 60), bool)
    mask[5:35, 5:55] = True
    unseen = mask.copy()
    unseen[5:35, 30:55] = False  # the right half is observed: a large part, it stays observed
    unseen[15:17, 12:14] = False  # a 2x2 observed island inside the unseen half: it goes back
    filled = fill_islands(unseen, mask, 20)
    assert filled[15:17, 12:14].all()
    np.testing.assert_array_equal(filled[:, 30:], unseen[:, 30:])
    assert not (filled & ~mask).any() and (filled >= unseen).all()
    np.testing.assert_array_equal(fill_islands(unseen, mask, 0), unseen)  # 0: off
    with pytest.raises(ValueError, match="RefineConfig.island_px"):
        RefineConfig(island_px=-1)


def test_enclosed_observed_parts_go_back_to_the_unseen_core():
    from coin_cl.pipeline.refine_masks import enclosed_parts

    mask = np.zeros((40, 60), bool)
    mask[5:35, 5:60] = True  # reaches the image's right border
    observed = np.zeros_like(mask)
    observed[5:35, 5:12] = True  # along the mask's left edge: touches the outside, stays observed
    observed[15:25, 25:40] = True  # 150 px in the middle of the unseen core: enclosed
    observed[10:14, 55:60] = True  # at the image border, unseen all around inside the frame: enclosed
    got = enclosed_parts(observed, mask)
    assert got[15:25, 25:40].all() and got[10:14, 55:60].all()
    assert not got[:, :12].any()
    assert got.sum() == 150 + 20
    assert not enclosed_parts(np.zeros_like(mask), mask).any()
    # a diagonal contact with the outside counts as touching it (8-neighbourhood)
    full = np.ones((10, 10), bool)
    full[4, 4] = False  # the only pixel outside
    diag = np.zeros_like(full)
    diag[5, 5] = True
    assert not enclosed_parts(diag, full).any()
    diag[5, 5], diag[7, 7] = False, True  # two pixels away: enclosed
    assert enclosed_parts(diag, full)[7, 7]
    with pytest.raises(ValueError, match="RefineConfig.enclosed"):
        RefineConfig(enclosed=1)


def test_fit_check_trusts_a_fit_only_where_it_beats_one_flat_colour_around_the_mask():
    from coin_cl.pipeline.refine_masks import fit_reproduces

    rng = np.random.default_rng(0)
    image = rng.uniform(0.2, 0.8, (40, 60, 3))
    mask = np.zeros((40, 60), bool)
    mask[12:28, 20:40] = True
    assert fit_reproduces(image + 0.01, image, mask, 4)  # close to the capture around the mask
    flat = np.broadcast_to(np.median(image[~mask], 0), image.shape)
    assert not fit_reproduces(flat, image, mask, 4)  # a flat colour does not beat itself
    assert not fit_reproduces(image[:, ::-1], image, mask, 4)  # texture in the wrong place
    plain = np.full_like(image, 0.5)
    assert not fit_reproduces(plain + 0.001, plain, mask, 4)  # nothing to beat on a plain ring
    nan = image.copy()
    nan[:, :10] = np.nan  # non-finite pixels are left out, not propagated
    assert fit_reproduces(nan, image, mask, 4)
    assert not fit_reproduces(np.full_like(image, np.nan), image, mask, 4)
    assert not fit_reproduces(image, image, np.ones((40, 60), bool), 4)  # no ring at all


def test_fit_check_gives_up_the_observed_part_of_views_the_fit_misses(capture, refined, tmp_path):
    """On the synthetic room the fit reproduces every view, so the check changes no split; a view
    whose render is replaced by a flat colour keeps no observed part."""
    from coin_cl.pipeline.refine_masks import fit_renders, split_view

    syn, scene = capture
    out, _ = refined
    train, masks = list(scene.train_idx), _dilated(scene)
    shutil.copytree(out / "default" / "gs", tmp_path / "gs")
    renders, _, _ = fit_renders(scene, masks, train, tmp_path / "gs", RefineConfig(), 300)
    checked, unchecked = RefineConfig(), RefineConfig(fit_check=False)
    for i in train:
        assert np.array_equal(split_view(scene, masks, renders, i, train, checked)[0],
                              split_view(scene, masks, renders, i, train, unchecked)[0])  # fmt: skip
    i = max(train, key=lambda j: (masks[j] & ~split_view(scene, masks, renders, j, train, checked)[0]).sum())
    assert (masks[i] & ~split_view(scene, masks, renders, i, train, checked)[0]).any()  # an observed part
    img, alpha, depth, cap_depth = renders[i]
    renders[i] = (np.full_like(img, 0.5), alpha, depth, cap_depth)
    assert np.array_equal(split_view(scene, masks, renders, i, train, checked)[0], masks[i])
