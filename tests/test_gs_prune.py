"""Point pruning by mask votes (coin_cl.gs.prune) on the synthetic room, against a brute-force count."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from coin_cl.gs.prune import in_masks, prune_points_in_masks
from coin_cl.scene.types import Camera


@pytest.fixture(scope="module")
def room():
    """Six low-resolution cameras around the synthetic room's object, with ray-cast object masks."""
    from coin_cl.scene import synthetic as syn

    boxes = syn.default_room(0)
    obj = next(b for b in boxes if b.is_object)
    cams = syn.arc_cameras(6, 90, 64, 48, obj.center, seed=0)
    masks = []
    for c in cams:
        ys, xs = np.mgrid[0 : c.height, 0 : c.width]
        t = syn.trace(boxes, c, xs.ravel() + 0.5, ys.ravel() + 0.5, colour=False)
        masks.append(t["object"].reshape(c.height, c.width))
    return boxes, obj, cams, masks


def _brute_votes(points, cams, masks):
    """Independent count via scene.types.Camera.project / in_image, one point at a time."""
    seen = np.zeros(len(points), int)
    inside = np.zeros(len(points), int)
    for c, m in zip(cams, masks):
        for j, p in enumerate(points):
            uv, z = c.project(p[None])
            if z[0] > 0.01 and c.in_image(uv)[0]:
                seen[j] += 1
                inside[j] += int(m[int(np.floor(uv[0, 1])), int(np.floor(uv[0, 0]))])
    return seen, inside


def test_prune_removes_exactly_points_in_masks(room):
    boxes, obj, cams, masks = room
    assert all(m.any() for m in masks)
    rng = np.random.default_rng(1)
    # Points well inside the object (a 40% margin: bigger than a pixel's footprint there).
    local = rng.uniform(-0.6, 0.6, (150, 3)) * obj.half
    on_obj = local @ obj.R.T + obj.center
    # Points on the far wall and on the floor in front of it.
    wall = np.stack([rng.uniform(-2.5, 2.5, 100), np.full(100, 2.99), rng.uniform(0.2, 2.3, 100)], 1)
    floor = np.stack([rng.uniform(-2.5, 2.5, 100), rng.uniform(1.0, 2.5, 100), np.full(100, 0.01)], 1)
    # Points on the table top around the object: inside the mask in some views only.
    top = np.stack([rng.uniform(-0.5, 0.5, 150), rng.uniform(-0.4, 0.4, 150), np.full(150, 0.5)], 1)
    pts = np.concatenate([on_obj, wall, floor, top]).astype(np.float32)

    seen, inside = _brute_votes(pts, cams, masks)
    for frac in (0.5, 1.0):
        res = prune_points_in_masks(pts, cams, masks, min_fraction=frac)
        expected = (seen >= 1) & (inside >= frac * seen)
        assert np.array_equal(~res.keep, expected)
        assert res.n_removed == int(expected.sum())
        assert np.array_equal(res.points, pts[res.keep]) and res.points.dtype == np.float32
    res = prune_points_in_masks(pts, cams, masks, min_fraction=0.5)
    assert not res.keep[:150].any()  # every object point goes
    assert (inside[150:] == 0).sum() > 100 and res.keep[inside == 0].all()  # never in a mask: stays
    # Background behind the object is inside the masks from part of the arc; there is no
    # occlusion test (the hole's background is inpainted anyway): it goes where that is most views.
    behind = (inside[150:] > 0) & (inside[150:] < seen[150:])
    b_in, b_seen = inside[150:][behind], seen[150:][behind]
    assert behind.any() and np.array_equal(~res.keep[150:][behind], 2 * b_in >= b_seen)
    # Table-top points partly hidden by the object: only some go at 0.5, fewer at 1.0.
    n_top_half = int((~res.keep[350:]).sum())
    n_top_all = int((~prune_points_in_masks(pts, cams, masks, min_fraction=1.0).keep[350:]).sum())
    assert 0 <= n_top_all <= n_top_half < 150


def test_prune_accepts_torch_inputs_and_checks_input(room):
    _, obj, cams, masks = room
    # Cameras built from torch tensors, masks as tensors.
    gcams = [Camera(torch.from_numpy(c.K), torch.from_numpy(c.viewmat), c.width, c.height) for c in cams]
    tmasks = [torch.from_numpy(m) for m in masks]
    pts = obj.center[None] + np.zeros((3, 3))
    assert prune_points_in_masks(pts, gcams, tmasks).n_removed == 3
    # A point behind every camera is seen by none and kept.
    far = np.array([[0.0, 0.0, 100.0]])
    assert prune_points_in_masks(far, cams, masks).n_removed == 0
    with pytest.raises(ValueError, match="cameras"):
        prune_points_in_masks(pts, cams, masks[:-1])
    with pytest.raises(ValueError, match="mask"):
        prune_points_in_masks(pts, cams[:1], [masks[0][:10]])
    with pytest.raises(ValueError, match="min_fraction"):
        prune_points_in_masks(pts, cams, masks, min_fraction=0.0)


def test_in_masks_is_the_vote_rule_with_min_views(room):
    """`in_masks` (the rule insertion's hull and mask refinement share) against the brute count:
    min_views leaves points seen by too few views out, whatever their votes."""
    _, obj, cams, masks = room
    rng = np.random.default_rng(2)
    pts = obj.center + rng.uniform(-1.5, 1.5, (300, 3))
    seen, inside = _brute_votes(pts, cams, masks)
    for frac, views in ((0.5, 1), (0.5, 4), (1.0, 6)):
        expected = (seen >= views) & (inside >= frac * seen)
        got = in_masks(torch.from_numpy(pts), cams, masks, frac, views)
        assert np.array_equal(got, expected)
    assert ((seen >= 1) & (seen < 4) & (inside == seen)).any()  # the min_views case is exercised
