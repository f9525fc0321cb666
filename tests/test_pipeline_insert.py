"""Insertion from one edited view (coin_cl.pipeline.insert, `coin-cl run --edited-ref`) on the synthetic
room's insertion task: the captured views show the room without the red box, the masks are its
footprint, the reference is edited by pasting the box's true appearance into it. The pipeline must
put the box's colour into the other views at the projected location and nowhere else."""

import json
from dataclasses import replace

import numpy as np
import pytest
from coin_cl.diffusion.scene_prior import ScenePriorConfig

from coin_cl.cli import main
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.coin import CoInConfig, inpaint
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
from coin_cl.pipeline.insert import InsertConfig, hull_depth, load_edited
from coin_cl.pipeline.ted import TEDConfig
from coin_cl.scene import load_scene, write_synthetic
from coin_cl.scene.io import read_image, write_png
from coin_cl.scene.masks import dilate_mask
from coin_cl.scene.synthetic import make_synthetic, paste_object

# Scaffold-GS learns the new object through its MLPs, slowly: 300 Ref-GS steps carry about a
# quarter of the box's colour into the other views (measured); the naive alternative carries none.
SMALL = CoInConfig(
    iters_refgs=300, iters_ted_finetune=20, iters_ted_adversarial=0, prior_seconds=5,
    inpaint2d=Inpaint2DConfig(prior=ScenePriorConfig(patch=32, base=8, max_steps=4)),
    clg=CLGConfig(steps=3), ted=TEDConfig(n_patches=2), refgs=RefGSConfig(depth_prior_iters=10),
)  # fmt: skip


def redness(img: np.ndarray) -> np.ndarray:
    """How red each pixel is: R minus the larger of G and B, (H, W)."""
    return img[..., 0] - img[..., 1:].max(-1)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("ins"), n_views=12, width=96, height=72, seed=0,
                           n_points=3000, task="insertion")  # fmt: skip


@pytest.fixture(scope="module")
def edit(room):
    """(scene, reference view, edited image): the training view with the largest footprint, with
    the box pasted in."""
    scene = load_scene(room)
    k = max(scene.train_idx, key=lambda i: scene.masks[i].sum())
    return scene, k, paste_object(scene.images[k], scene.extras["object_present"][k], scene.masks[k])


@pytest.fixture(scope="module")
def run(edit, tmp_path_factory):
    scene, k, edited = edit
    out = tmp_path_factory.mktemp("run")
    return out, inpaint(scene, out, config=replace(SMALL, mask_dilate=1), edited_ref=edited)


@pytest.fixture(scope="module")
def naive(edit, tmp_path_factory):
    """The naive alternative: plain Scaffold-GS on the edited reference beside the unedited views."""
    scene, k, edited = edit
    out = tmp_path_factory.mktemp("naive")
    cfg = replace(SMALL, mask_dilate=1, skip=("refgs", "clg", "ted"), insert=InsertConfig(propagate=False),
                  iters_refgs=SMALL.iters_refgs + SMALL.iters_ted_finetune)  # fmt: skip
    return out, inpaint(scene, out, config=cfg, edited_ref=edited)


def colour_gains(scene, k, out):
    """Per non-reference view: the share of the way from the empty room's redness to the box's that
    the render goes inside the box's true footprint, and how much more of the render than of the
    empty room is red far from the mask (outside its 3D region)."""
    gains, leaks = [], []
    for i in [i for i in scene.train_idx if i != k] + list(scene.test_idx):
        stem = scene.cameras[i].name.rsplit(".", 1)[0]
        render = read_image(out / "eval" / "renders" / f"{stem}.png")
        foot = scene.masks[i]
        gt = scene.extras["object_present"][i] if i in scene.train_idx else scene.images[i]
        empty = scene.images[i] if i in scene.train_idx else scene.extras["object_absent"][i]
        gains.append(
            (redness(render)[foot].mean() - redness(empty)[foot].mean())
            / (redness(gt)[foot].mean() - redness(empty)[foot].mean())
        )
        far = ~dilate_mask(foot, kernel=3, iterations=4)
        leaks.append(np.mean(redness(render)[far] > 0.25) - np.mean(redness(empty)[far] > 0.25))
    return np.array(gains), np.array(leaks)


def test_ref_gs_and_clg_settings_of_an_insertion():
    """Ref-GS and CLG as an insertion sets them (stages.refgs_settings, coin_plan.clg_skip_reason):
    no background depth, whole views weighed; with the object lifted from one photo every view
    the same; CLG left out wherever stage 1 lifted the object, and only there."""
    from coin_cl.pipeline.coin_plan import clg_skip_reason
    from coin_cl.pipeline.stages import refgs_settings

    edited = np.zeros((4, 4, 3), np.float32)
    removal = refgs_settings(SMALL, 0, None)
    assert removal.bg_depth and removal.adaptive_weights and removal.weight_region == "mask"
    hull = refgs_settings(replace(SMALL, insert=InsertConfig(regions="hull")), 0, edited)
    assert not hull.bg_depth and hull.weight_region == "view" and hull.adaptive_weights
    one = refgs_settings(replace(SMALL, insert=InsertConfig(regions="derive")), 0, edited)
    assert not one.bg_depth and one.weight_region == "view" and not one.adaptive_weights
    prompt = refgs_settings(replace(SMALL, prompt="a red box"), 0, None)
    assert not prompt.bg_depth and prompt.adaptive_weights  # SD2's per-view fills need the arbiter
    assert one.ref == 0 and one.seed == SMALL.seed
    assert clg_skip_reason(SMALL, None).startswith("no sampler")  # a removal without SD2 (test_coin_plan)
    assert clg_skip_reason(replace(SMALL, skip=("clg",)), edited).startswith("asked")
    assert clg_skip_reason(SMALL, edited).startswith("an insertion")
    assert clg_skip_reason(replace(SMALL, insert=InsertConfig(propagate=False)), edited) is None


def test_insertion_ground_truth_generator():
    s = make_synthetic(n_views=8, width=64, height=48, task="insertion", n_points=500)
    train = [j for j in range(8) if not s.is_test[j]]
    # the object is the red box, seen in every view, and absent from the captured images
    assert all(s.masks[j].any() for j in range(8))
    j = train[0]
    m = s.masks[j]
    assert redness(s.present[j])[m].mean() > redness(s.absent[j])[m].mean() + 0.15
    np.testing.assert_array_equal(s.present[j][~m], s.absent[j][~m])
    # it stands in front of the room (edge pixels of the footprint may see the room at their centre)
    assert (s.depth_present[j] <= s.depth_absent[j]).all()
    assert (s.depth_present[j][m] < s.depth_absent[j][m]).mean() > 0.7
    np.testing.assert_array_equal(paste_object(s.absent[j], s.present[j], m), s.present[j])


def test_hull_depth_finds_the_object_surface(edit):
    scene, k, edited = edit
    train = list(scene.train_idx)
    gt = scene.extras["depth"]  # training views hold the capture's depth (no object): the table/wall
    cam = scene.cameras[k]
    masks = [scene.masks[i] for i in train]
    d = hull_depth(cam, scene.masks[k], [scene.cameras[i] for i in train], masks, 0.05, 10.0, InsertConfig())
    m = scene.masks[k]
    ok = np.isfinite(d) & m
    assert ok.mean() / m.mean() > 0.8  # exact silhouettes: some edge pixels miss the hull
    # the visual hull's front lies in front of what the capture sees there, and near the box (~0.2 m deep)
    assert (d[ok] < gt[k][ok]).mean() > 0.95
    present = make_synthetic(n_views=12, width=96, height=72, seed=0, n_points=3000, task="insertion")
    dp = present.depth_present[k]
    assert np.median(np.abs(d[ok] - dp[ok])) < 0.15


def test_object_appears_in_the_other_views_and_nowhere_else(edit, run, naive):
    scene, k, _ = edit
    out, res = run
    status = {n: r["status"] for n, r in res.stages.items()}
    assert status.pop("3_clg").startswith("skipped: an insertion")  # stage 1's warps are TE-D's targets
    assert list(status.values()) == ["ran"] * 5
    assert res.stages["1_inpaint"]["result"]["lifted_points"] > 0
    gains, leaks = colour_gains(scene, k, out)
    naive_gains, _ = colour_gains(scene, k, naive[0])
    assert np.median(gains) > max(0.12, 3 * np.median(naive_gains)), (gains, naive_gains)
    assert leaks.max() < 0.01, leaks
    # scored against the box's ground truth in the test views: better than the naive alternative
    assert res.metrics["m_psnr"] > naive[1].metrics["m_psnr"] + 0.5
    # an insertion restarts TE-D's learning rates (TEDConfig.rates "auto"; a continued fit leaked)
    ted = json.loads((out / "4_ted" / "manifest.json").read_text())["settings"]["cfg"]
    refgs = json.loads((out / "2_refgs" / "manifest.json").read_text())["settings"]
    assert ted["rates"] == "restart" and refgs["schedule_iters"] == refgs["iters"]


def test_edited_image_hash_reruns_from_stage_1(edit, run, tmp_path):
    import shutil

    scene, k, edited = edit
    out = tmp_path / "copy"
    shutil.copytree(run[0], out)
    cfg = replace(SMALL, mask_dilate=1)  # the run's own (skipping TE-D would change Ref-GS's schedule)
    res = inpaint(scene, out, config=cfg, edited_ref=edited)
    st = {n: r["status"] for n, r in res.stages.items()}
    assert st["1_inpaint"] == st["2_refgs"] == "skipped: up to date"
    other = edited.copy()
    other[scene.masks[k]] = other[scene.masks[k]][:, ::-1]  # a differently coloured box
    res = inpaint(scene, out, config=cfg, edited_ref=other)
    st = {n: r["status"] for n, r in res.stages.items()}
    assert st["0_scene"] == "skipped: up to date" and st["1_inpaint"] == "ran" and st["2_refgs"] == "ran"


def test_bad_edited_reference_is_a_clear_error(edit, room, tmp_path):
    scene, k, edited = edit
    with pytest.raises(FileNotFoundError, match="nope.png"):
        inpaint(scene, tmp_path / "a", config=SMALL, edited_ref=tmp_path / "nope.png")
    with pytest.raises(ValueError, match="48x36 but the reference view is 96x72"):
        inpaint(scene, tmp_path / "b", config=SMALL, edited_ref=edited[::2, ::2])
    bad = edited.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        inpaint(scene, tmp_path / "c", config=SMALL, edited_ref=bad)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        inpaint(scene, tmp_path / "d", config=SMALL, edited_ref=edited * 255)
    with pytest.raises(ValueError, match="nothing to insert"):
        inpaint(scene, tmp_path / "e", config=SMALL, edited_ref=scene.images[k], reference=k)
    with pytest.raises(ValueError, match="not both"):
        inpaint(scene, tmp_path / "f", config=SMALL, edited_ref=edited, prompt="a red box")
    # uint8 and the captured size at a lower run resolution are accepted
    u8 = (edited * 255 + 0.5).astype(np.uint8)
    np.testing.assert_allclose(load_edited(u8, (96, 72)), edited, atol=1 / 255)
    assert load_edited(u8, (48, 36), (96, 72)).shape == (36, 48, 3)
    assert not any((tmp_path / p / "1_inpaint").exists() for p in "abcdef")


def test_cli_edited_ref(edit, room, tmp_path, capsys):
    scene, k, edited = edit
    write_png(tmp_path / "edited.png", edited)
    rc = main(["run", str(room), "--out", str(tmp_path / "cli"), "--edited-ref", str(tmp_path / "edited.png"),
               "--iters", "3", "--skip-stage", "clg", "--skip-stage", "ted"])  # fmt: skip
    assert rc == 0
    rows = {ln.split()[0]: ln.split() for ln in capsys.readouterr().out.splitlines() if ln.startswith("  1_")}
    assert rows["1_inpaint"][-1] == "ran"
    rc = main(["run", str(room), "--out", str(tmp_path / "cli2"), "--edited-ref", str(tmp_path / "none.png")])
    assert rc == 2 and "none.png" in capsys.readouterr().err
