"""coin_cl.agreement on the synthetic room, whose geometry and object-free images are exact: views
of one 3D scene agree (the ruler's floor), per-view solid colours disagree by their differences, and
degenerate input gives a documented result."""

import numpy as np
import pytest

from coin_cl.agreement import cross_view_agreement, neighbour_pairs, pair_agreement
from coin_cl.scene.synthetic import make_synthetic


@pytest.fixture(scope="module")
def syn():
    return make_synthetic(coverage=180, n_views=12, width=96, height=72, n_points=500, seed=0)


def _train(syn):
    idx = [i for i, t in enumerate(syn.is_test) if not t]
    return idx, [syn.cameras[i] for i in idx]


def test_views_of_one_scene_agree_and_per_view_colours_do_not(syn):
    idx, cams = _train(syn)
    regions = [syn.masks[i] for i in idx]
    depths = [syn.depth_absent[i] for i in idx]
    truth = [syn.absent[i] for i in idx]
    pairs, s = cross_view_agreement(cams, truth, regions, depths)
    assert len(pairs) == 2 * len(idx) and s["pairs"] >= len(idx)  # neighbours see each other's hole
    assert s["coverage"] > 0.3
    # the object-free room seen from two views: nearest-pixel sampling of its textures alone
    assert s["disagreement"] < 0.06, s
    # every view paints its hole its own solid colour: the pairs differ by about their colours
    rng = np.random.default_rng(1)
    colours = rng.uniform(0, 1, (len(idx), 3))
    solid = [np.where(r[..., None], c, t) for r, c, t in zip(regions, colours, truth, strict=True)]
    per_pair, s2 = cross_view_agreement(cams, solid, regions, depths)
    for p in per_pair:
        if p.pixels:
            assert p.disagreement == pytest.approx(np.abs(colours[p.dst] - colours[p.src]).mean(), abs=1e-9)
    assert s2["disagreement"] > 4 * s["disagreement"] and s2["coverage"] == s["coverage"]


def test_an_occluder_in_the_source_view_is_not_compared(syn):
    """A pixel whose carried point is hidden in the source view (its depth there nearer than the
    point) is left out, not compared with the occluder's colour."""
    idx, cams = _train(syn)
    j, i = neighbour_pairs(cams)[0]
    region, depth = syn.masks[idx[j]], syn.depth_absent[idx[j]]
    n0, cov0, _ = pair_agreement(cams[j], cams[i], syn.absent[idx[j]], syn.absent[idx[i]], region,
                                 syn.masks[idx[i]], depth, syn.depth_absent[idx[i]])  # fmt: skip
    nearer = np.where(syn.masks[idx[i]], 0.5 * syn.depth_absent[idx[i]], syn.depth_absent[idx[i]])
    n1, cov1, dis1 = pair_agreement(cams[j], cams[i], syn.absent[idx[j]], syn.absent[idx[i]], region,
                                    syn.masks[idx[i]], depth, nearer)  # fmt: skip
    assert n0 > 0 and n1 == 0 and cov1 == 0.0 and np.isnan(dis1)


def test_empty_regions_unknown_depth_and_nan_are_documented(syn):
    idx, cams = _train(syn)
    img, dep = syn.absent[idx[0]], syn.depth_absent[idx[0]]
    empty = np.zeros(img.shape[:2], bool)
    assert pair_agreement(cams[0], cams[1], img, img, empty, empty, dep, dep)[:2] == (0, 0.0)
    nan_depth = np.full(img.shape[:2], np.nan)
    assert (
        pair_agreement(cams[0], cams[1], img, img, syn.masks[idx[0]], syn.masks[idx[1]], nan_depth, dep)[0]
        == 0
    )
    # NaN colours count as black, never as a NaN figure
    bad = np.array(syn.absent[idx[1]], np.float64)
    bad[syn.masks[idx[1]]] = np.nan
    _, s = cross_view_agreement(cams[:2], [syn.absent[idx[0]], bad], [syn.masks[i] for i in idx[:2]],
                                [syn.depth_absent[i] for i in idx[:2]])  # fmt: skip
    assert np.isfinite(s["disagreement"]) or s["pixels"] == 0
    _, none = cross_view_agreement(cams[:1], [img], [empty], [dep])
    assert none["pairs"] == 0 and np.isnan(none["disagreement"])
    with pytest.raises(ValueError, match="one of each per view"):
        cross_view_agreement(cams[:2], [img], [empty, empty], [dep, dep])
