"""The CLG energy of one view (coin_cl.pipeline.clg_energy) on the synthetic room with exact
geometry: the object-absent truth has a lower energy than an inconsistent inpaint, the gradient
stays inside the hole, and a fully masked crop is refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from coin_cl.diffusion import AnalyticFeatures, opencv_inpaint

from coin_cl.crop import crop_image, resize_to
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.clg_energy import make_energy, setup_view
from coin_cl.pipeline.reference import reference_points
from coin_cl.scene.synthetic import make_synthetic

WORK = 64


@pytest.fixture(scope="module")
def view():
    s = make_synthetic(n_views=8, width=128, height=96, n_points=2000)
    train = [i for i in range(len(s.cameras)) if not s.is_test[i]]
    k, n = train[0], train[2]
    pk = reference_points(s.cameras[k], s.depth_absent[k], s.masks[k])
    inp = opencv_inpaint(s.present[n], s.masks[n])
    feats, cfg = AnalyticFeatures(), CLGConfig()
    prob = setup_view(s.cameras[k], s.cameras[n], s.absent[k], inp, s.absent[n], s.depth_absent[k],
                      s.depth_absent[n], s.masks[n], pk, feats, WORK, cfg, None)  # fmt: skip
    return s, n, prob, make_energy(prob, feats, cfg, None)


def _work_crop(img: np.ndarray, prob) -> torch.Tensor:
    c = resize_to(crop_image(img, prob.y0, prob.x0, prob.side, prob.side), WORK, WORK)
    return torch.from_numpy(np.ascontiguousarray(c.transpose(2, 0, 1)))[None].float()


def test_truth_has_lower_energy_than_an_inconsistent_fill(view):
    s, n, prob, energy = view
    assert prob.image.shape == (1, 3, WORK, WORK) and int(prob.support.sum()) > 20
    assert int((prob.support & (prob.hole[0, 0] == 0)).sum()) == 0  # S lies inside the hole
    e_inp = float(energy(prob.image))
    e_true = float(energy(_work_crop(s.absent[n], prob)))
    # the truth's floor (0.19 here) is the resampling of fine texture at 64 px, as in the residual
    assert np.isfinite(e_inp) and e_true < 0.8 * e_inp


def test_gradient_stays_in_the_hole(view):
    _, _, prob, energy = view
    x = prob.image.clone().requires_grad_(True)
    energy(x).backward()
    g = x.grad[0].abs().sum(0)
    hole = prob.hole[0, 0] > 0
    assert float(g[~hole].max()) == 0.0 and float(g[hole].max()) > 0.0
    with pytest.raises(ValueError, match="working crop"):
        energy(prob.image[..., :-1])


def test_fully_masked_crop_is_refused(view):
    s, n, _, _ = view
    full = np.ones_like(s.masks[n])
    pk = reference_points(s.cameras[n], s.depth_absent[n], s.masks[n])
    with pytest.raises(ValueError, match="entirely masked"):
        setup_view(s.cameras[n], s.cameras[n], s.absent[n], s.absent[n], s.absent[n], None, None, full, pk,
                   AnalyticFeatures(), WORK, CLGConfig(), None)  # fmt: skip
