"""The embedded ground-truth scene: determinism, coverage, ground truth, and a round trip through
the loader with exact geometry checks."""

import shutil

import numpy as np
import pytest

from coin_cl.scene import load_scene
from coin_cl.scene.synthetic import make_synthetic, trace, write_synthetic

SMALL = dict(n_views=12, width=80, height=60, n_points=3000)


@pytest.fixture(scope="module")
def syn():
    return make_synthetic(coverage=180, seed=3, **SMALL)


@pytest.fixture(scope="module")
def syn_dir(syn, tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("syn") / "scene", syn)


def test_deterministic_per_seed(syn):
    again = make_synthetic(coverage=180, seed=3, **SMALL)
    other = make_synthetic(coverage=180, seed=4, **SMALL)
    np.testing.assert_array_equal(again.present[5], syn.present[5])
    np.testing.assert_array_equal(again.points, syn.points)
    assert not np.array_equal(other.present[5], syn.present[5])


@pytest.mark.parametrize("coverage", [90, 180, 360])
def test_coverage_arc(coverage):
    s = make_synthetic(coverage=coverage, n_views=8, width=32, height=24, n_points=100, seed=0)
    obj = s.boxes[-1].center
    az = np.degrees([np.arctan2(*(c.center - obj)[[1, 0]]) for c in s.cameras])
    rel = (az + 90 + 180) % 360 - 180  # azimuth relative to the arc's centre (-90 deg)
    if coverage == 360:
        gaps = np.diff(np.sort(rel))
        assert gaps.max() < 360 / 8 * 1.5 and np.ptp(rel) > 270  # evenly all around
    else:
        assert np.ptp(rel) == pytest.approx(coverage, abs=8)
    # every camera looks at the object: it projects near the image centre
    for c in s.cameras:
        uv, z = c.project(obj[None])
        assert z[0] > 0 and np.abs(uv[0] - [16, 12]).max() < 6


def test_ground_truth_consistency(syn):
    n_test = sum(syn.is_test)
    assert n_test == 3 and syn.is_test[:n_test] == [True] * 3
    for j in range(len(syn.cameras)):
        m = syn.masks[j]
        assert 0.005 < m.mean() < 0.5  # the object is in every view, not filling it
        # Outside the mask the two renders agree exactly; inside they differ.
        np.testing.assert_array_equal(syn.present[j][~m], syn.absent[j][~m])
        assert np.abs(syn.present[j][m] - syn.absent[j][m]).mean() > 0.02
        # The object is in front of what it hides.
        dp, da = syn.depth_present[j], syn.depth_absent[j]
        assert np.all(dp <= da + 1e-6) and np.all(dp[~m] == da[~m])
    assert syn.points.shape == (3000, 3) and syn.colors.shape == (3000, 3)


def test_round_trip_through_loader(syn, syn_dir):
    sc = load_scene(syn_dir)
    assert sc.names == [c.name for c in syn.cameras]
    assert sc.test_idx == [0, 1, 2] and sc.train_idx == list(range(3, 12))
    for j, (a, b) in enumerate(zip(sc.cameras, syn.cameras, strict=True)):
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-6)
        np.testing.assert_allclose(a.K, b.K, atol=1e-6)
        assert (a.width, a.height) == (80, 60)
        want = syn.absent[j] if syn.is_test[j] else syn.present[j]
        np.testing.assert_allclose(sc.images[j], want, atol=0.5 / 255 + 1e-6)
        np.testing.assert_array_equal(sc.masks[j], syn.masks[j])
    np.testing.assert_allclose(sc.points, syn.points, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(sc.colors, syn.colors, atol=0.5 / 255 + 1e-6)
    # ground-truth extras come back too
    assert set(sc.extras["object_absent"]) == set(sc.train_idx)
    np.testing.assert_array_equal(sc.extras["depth"][4], syn.depth_present[4])
    assert sc.near is not None and np.all(sc.near < sc.far)


def test_llff_poses_match_colmap(syn_dir, tmp_path):
    # Same scene with the COLMAP images removed: poses come from poses_bounds.npy.
    d = tmp_path / "llff"
    shutil.copytree(syn_dir, d)
    (d / "sparse" / "0" / "images.bin").unlink()
    a, b = load_scene(syn_dir), load_scene(d)
    assert b.meta["poses"].endswith("poses_bounds.npy")
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        np.testing.assert_allclose(cb.viewmat, ca.viewmat, atol=1e-6)
        np.testing.assert_allclose(cb.K, ca.K, atol=1e-9)
    np.testing.assert_allclose(b.points, a.points)  # points3D.bin read without images.bin


def test_reprojection_between_views_within_half_pixel(syn, syn_dir):
    sc = load_scene(syn_dir)
    rng = np.random.default_rng(0)
    W, H = 80, 60
    checked = 0
    for a, b in [(3, 4), (5, 8), (10, 11), (0, 6)]:
        ca, cb = sc.cameras[a], sc.cameras[b]
        depth_a = syn.depth_absent[a] if syn.is_test[a] else syn.depth_present[a]
        ys, xs = rng.integers(0, H, 300), rng.integers(0, W, 300)
        uv = np.stack([xs + 0.5, ys + 0.5], 1)
        X = ca.unproject(uv, depth_a[ys, xs].astype(np.float64))  # loaded camera A + ray-cast depth
        uvb, zb = cb.project(X)
        vis = cb.in_image(uvb) & (zb > 0)
        # Cast B's own rays (independent ray caster) through the projected positions.
        r = trace(syn.boxes, syn.cameras[b], uvb[vis, 0], uvb[vis, 1], colour=False)
        key = "depth_absent" if syn.is_test[b] else "depth_present"
        # Present/absent must match in A and B for the point to be the same surface.
        if syn.is_test[a] != syn.is_test[b]:
            key = "depth_absent"
        unoccluded = np.abs(r[key] - zb[vis]) < 1e-3 * zb[vis]
        assert unoccluded.mean() > 0.5
        Xb = cb.unproject(uvb[vis][unoccluded], r[key][unoccluded])
        uva, _ = ca.project(Xb)
        err = np.linalg.norm(uva - uv[vis][unoccluded], axis=1)
        assert err.max() < 0.5
        checked += unoccluded.sum()
    assert checked > 500


def test_make_scene_cli(tmp_path):
    from coin_cl.cli import main

    out = tmp_path / "cli_scene"
    rc = main(
        [
            "make-scene",
            str(out),
            "--coverage",
            "90",
            "--seed",
            "1",
            "--views",
            "8",
            "--width",
            "48",
            "--height",
            "32",
        ]
    )
    assert rc == 0
    sc = load_scene(out)
    assert len(sc) == 8 and sc.images[0].shape == (32, 48, 3) and len(sc.test_idx) == 2


def test_points_only_from_training_views():
    """The "SfM" points are what the training views capture: every point lies on a surface some
    training view sees (its depth there within 1 %). Points taken from the object-absent test views
    would put the truth behind the object into the initial model."""
    s = make_synthetic(coverage=90, seed=0, n_views=16, width=96, height=72, n_points=6000)
    seen = np.zeros(len(s.points), bool)
    for j, cam in enumerate(s.cameras):
        if s.is_test[j]:
            continue
        px, ok = cam.pixels(s.points)
        _, z = cam.project(s.points)
        d = s.depth_present[j][px[:, 1], px[:, 0]]
        seen |= ok & (np.abs(z - d) <= 0.01 * d)
    assert len(s.points) == 6000
    assert seen.all(), f"{(~seen).sum()} points no training view captures"
