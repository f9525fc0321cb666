"""Reprojection through P_k and the residual to the reference (coin_cl.pipeline.reprojection), on the
synthetic room whose object-absent depth gives exact geometry."""

from __future__ import annotations

import numpy as np
import pytest
from coin_cl.diffusion import opencv_inpaint

from coin_cl.pipeline.reference import reference_points
from coin_cl.pipeline.reprojection import (
    consistency_residual,
    reference_in_view,
    residual_to_reference,
    warp_fill,
)
from coin_cl.scene.synthetic import make_synthetic


@pytest.fixture(scope="module")
def room():
    s = make_synthetic(n_views=8, width=128, height=96, n_points=2000)
    train = [i for i in range(len(s.cameras)) if not s.is_test[i]]
    k = train[0]
    pk = reference_points(s.cameras[k], s.depth_absent[k], s.masks[k])
    return s, train, k, pk


def test_residual_is_small_for_consistent_truth(room):
    # the metric itself: ground-truth object-absent images agree through the exact geometry, the
    # classical inpaints do not
    s, train, k, pk = room
    n = train[2]
    inp = opencv_inpaint(s.present[n], s.masks[n])
    r_true, n_sup = consistency_residual(s.absent[n], s.absent[k], s.cameras[n], s.cameras[k], pk, s.masks[n])
    r_inp, _ = consistency_residual(inp, s.absent[k], s.cameras[n], s.cameras[k], pk, s.masks[n])
    assert n_sup > 50
    # the floor of the truth (~0.06) is resampling of fine texture at 128x96, not geometry
    assert r_true < 0.8 * r_inp
    empty = np.zeros_like(s.masks[n])
    r, n0 = consistency_residual(s.absent[n], s.absent[k], s.cameras[n], s.cameras[k], pk, empty)
    assert n0 == 0 and np.isnan(r)  # no support: NaN, documented


def test_warp_fill_touches_only_the_mask(room):
    s, train, k, pk = room
    n = train[2]
    render = np.zeros_like(s.absent[n])
    warped, weight = reference_in_view(s.absent[k], s.cameras[n], s.cameras[k], pk)
    out, n_sup = warp_fill(s.present[n], render, s.masks[n], warped, weight)
    m = s.masks[n]
    assert np.array_equal(out[~m], s.present[n][~m])
    assert 0 < n_sup <= int(m.sum())
    # supported pixels take the reference's colour: close to the truth there; the rest the render (0)
    r, _ = consistency_residual(out, s.absent[k], s.cameras[n], s.cameras[k], pk, m)
    assert r < 0.05


def test_residual_to_reference_on_exact_geometry(room):
    s, train, k, _ = room
    n = len(s.cameras)
    regions = [s.masks[i] if i in train else None for i in range(n)]
    truth = residual_to_reference(s.cameras, s.depth_absent, s.absent, regions, k, s.absent[k], s.masks[k])
    inp = [opencv_inpaint(s.present[i], s.masks[i]) if i in train else None for i in range(n)]
    worse = residual_to_reference(s.cameras, s.depth_absent, inp, regions, k, s.absent[k], s.masks[k])
    assert truth < 0.1 and truth < 0.7 * worse
    # brute force for one view, pixel by pixel
    i = train[2]
    cam, ck = s.cameras[i], s.cameras[k]
    errs = []
    for y, x in zip(*np.nonzero(s.masks[i])):
        p = cam.unproject(np.array([[x + 0.5, y + 0.5]]), np.array([s.depth_absent[i][y, x]]))
        uv, z = ck.project(p)
        if z[0] > 0 and ck.in_image(uv)[0]:
            u, v = int(np.floor(uv[0, 0])), int(np.floor(uv[0, 1]))
            if s.masks[k][v, u]:
                errs.append(np.abs(inp[i][y, x] - s.absent[k][v, u]).mean())
    only = [r if j == i else None for j, r in enumerate(regions)]
    one = residual_to_reference(s.cameras, s.depth_absent, inp, only, k, s.absent[k], s.masks[k])
    assert len(errs) > 20 and one == pytest.approx(float(np.mean(errs)), rel=1e-5)
    nothing = residual_to_reference(s.cameras, s.depth_absent, inp, [None] * n, k, s.absent[k], s.masks[k])
    assert np.isnan(nothing)
