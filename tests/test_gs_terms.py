import math
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from coin_cl.checkpoint import load_checkpoint
from coin_cl.gs.gaussians import GaussianConfig
from coin_cl.gs.losses import LossConfig, photometric_loss
from coin_cl.gs.model_kinds import build_model
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel
from coin_cl.gs.strategy import DefaultStrategy
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.terms import (
    LossContext,
    LossTerm,
    NeedleReg,
    PhotometricLoss,
    ScaleVolumeReg,
    ViewWeights,
    default_terms,
)
from coin_cl.gs.trainer import CKPT_NAME, TrainConfig, Trainer

EXACT = "torch"


@pytest.fixture(scope="module")
def scene():
    return tiny_scene(n=30, width=24, height=16, n_views=6, backend=EXACT)


def _trainer(scene, terms, out=None, iters=3, backend=EXACT, callback=None, **kw):
    m = build_model("3dgs", scene.noisy_points(), None, 3.5, seed=0,
                    model_cfg=GaussianConfig(sh_degree_interval=10))  # fmt: skip
    cfg = TrainConfig(model="3dgs", iters=iters, backend=backend, progress=False, log_every=5,
                      export_ply=False, **kw)  # fmt: skip
    st = DefaultStrategy(refine_start=5, refine_every=8, reset_every=24)
    return Trainer(m, scene.views[1:], scene.views[:1], cfg, out, callback, strategy=st, terms=terms)


class MeansSquared(LossTerm):
    """A custom term: sum of squared means, gradient 2 x means."""

    name = "means_sq"

    def __init__(self, weight: float):
        self.weight = weight

    def __call__(self, ctx: LossContext) -> Tensor:
        return (ctx.model.optimizer.params["means"] ** 2).sum()


def test_custom_term_adds_its_weighted_gradient(scene):
    grads = {}
    for w in (None, 0.0, 0.5):
        terms = [PhotometricLoss()] + ([] if w is None else [MeansSquared(w)])
        tr = _trainer(scene, terms)
        means = tr.model.optimizer.params["means"].detach().clone()
        rec = tr.train_step()
        grads[w] = tr.model.optimizer.params["means"].grad.clone()
        if w is not None:
            assert math.isclose(rec["means_sq"], w * float((means**2).sum()), rel_tol=1e-6)
            assert math.isclose(rec["loss"], rec["photometric"] + rec["means_sq"], rel_tol=1e-6)
    assert torch.equal(grads[0.0], grads[None])  # weight 0: no contribution at all
    assert torch.allclose(grads[0.5], grads[None] + 0.5 * 2 * means, atol=1e-6)


def test_photometric_term_is_the_weighted_masked_loss(scene):
    v = scene.views[1]
    v2 = type(v)(v.camera, v.image, torch.zeros(16, 24, dtype=torch.bool), 0.25)
    v2.exclude[4:9, 3:12] = True
    img = torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(0), requires_grad=True)
    out = type("R", (), {"image": img, "meta": {}})()
    ctx = LossContext(view=v2, index=0, out=out, step=0, model=None)
    cfg = LossConfig(lambda_dssim=0.3)
    val = PhotometricLoss(cfg)(ctx)
    ref, parts = photometric_loss(img[None], v2.image[None], torch.tensor([0.25]), v2.exclude[None], cfg)
    assert torch.equal(val, ref)
    assert ctx.log["view_weight"] == 0.25 and ctx.log["l1"] == float(parts["l1"][0])
    (g,) = torch.autograd.grad(val, img)
    assert torch.count_nonzero(g[v2.exclude]) == 0


def test_weighted_regions_weigh_only_the_region_and_count_the_rest_once(scene):
    v = scene.views[1]
    view = type(v)(v.camera, v.image, torch.zeros(16, 24, dtype=torch.bool), 4.0)  # W_n = 4
    view.exclude[0:3, :] = True
    region = np.zeros((16, 24), bool)
    region[6:12, 8:20] = True
    img = torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(1), requires_grad=True)
    out = type("R", (), {"image": img, "meta": {}})()
    cfg = LossConfig(lambda_dssim=0.0)  # L1 alone: each pixel's gradient is its own
    grads, values = {}, {}
    for name, regions in (("view", None), ("region", [region])):
        ctx = LossContext(view=view, index=0, out=out, step=0, model=None)
        values[name] = PhotometricLoss(cfg, weighted_regions=regions)(ctx)
        (grads[name],) = torch.autograd.grad(values[name], img)
    r = torch.as_tensor(region)
    assert torch.allclose(grads["region"][r], grads["view"][r])  # W_n inside, as on the whole view
    assert torch.allclose(grads["region"][~r], grads["view"][~r] / 4.0)  # once outside
    assert torch.count_nonzero(grads["region"][view.exclude]) == 0
    _, parts = photometric_loss(img[None], view.image[None], None, view.exclude[None], cfg)
    per_px = (img - view.image).abs().mean(-1).detach()
    keep = ~view.exclude
    want = (per_px[keep & ~r].sum() + 4.0 * per_px[keep & r].sum()) / keep.sum()
    assert values["region"].item() == pytest.approx(want.item(), rel=1e-6)
    assert values["view"].item() == pytest.approx(4.0 * float(parts["loss"][0]), rel=1e-6)


class RefLikeWeights(ViewWeights):
    """Ref-GS-shaped adaptive weights: view `ref` gets `lam`; others 1 / (1 + exp(lam (L_t -
    L_prev))) from the change of their own loss since their previous visit (state per view)."""

    def __init__(self, n_views: int, ref: int = 0, lam: float = 50.0):
        self.ref, self.lam = ref, lam
        self.prev = torch.full((n_views,), float("nan"))

    def __call__(self, ctx: LossContext, view_loss: Tensor) -> float:
        i = ctx.index
        prev, self.prev[i] = float(self.prev[i]), float(view_loss)
        if i == self.ref:
            return self.lam
        return 1.0 if math.isnan(prev) else 1.0 / (1.0 + math.exp(self.lam * (float(view_loss) - prev)))

    def state_dict(self) -> dict[str, Any]:
        return {"prev": self.prev.clone()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.prev = sd["prev"].clone()


class ToyCritic(LossTerm):
    """A term with a parameter and optimiser of its own (the shape of an adversarial term): the
    generator sees `c * mean(image)`; after the model's step the critic fits c to the image."""

    name = "critic"
    weight = 0.1

    def __init__(self):
        self.c = torch.nn.Parameter(torch.tensor(1.0))
        self.opt = torch.optim.Adam([self.c], lr=0.05)
        self.calls: list[int] = []

    def __call__(self, ctx: LossContext) -> Tensor:
        return self.c.detach() * ctx.out.image.mean()

    def step_after(self, ctx: LossContext) -> None:
        self.calls.append(ctx.step)
        self.opt.zero_grad()
        ((self.c - ctx.out.image.detach().mean()) ** 2).backward()
        self.opt.step()

    def state_dict(self) -> dict[str, Any]:
        return {"c": self.c.detach().clone(), "opt": self.opt.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        with torch.no_grad():
            self.c.copy_(sd["c"])
        self.opt.load_state_dict(sd["opt"])


class Killed(Exception):
    pass


def test_stateful_terms_roundtrip_through_a_checkpoint_bit_exactly(scene, tmp_path):
    n = len(scene.views) - 1

    def terms():
        return [PhotometricLoss(view_weights=RefLikeWeights(n)), ToyCritic()]

    iters = 20
    at10 = {}

    def snap(tr, step):
        if step == 10:
            at10["photometric"] = tr.terms[0].state_dict()
            at10["critic"] = tr.terms[1].state_dict()

    ref = _trainer(scene, terms(), tmp_path / "ref", iters, "opencl", snap, ckpt_every=0)
    ref.train()
    assert ref.terms[1].calls == list(range(iters))  # once per step, after the model's step

    def kill(tr, step):
        if step == 13:
            raise Killed

    run = _trainer(scene, terms(), tmp_path / "run", iters, "opencl", kill, ckpt_every=10)
    with pytest.raises(Killed):
        run.train()
    saved = load_checkpoint(tmp_path / "run" / CKPT_NAME)
    assert set(saved["terms"]) == {"photometric", "critic"}
    resumed = _trainer(scene, terms(), tmp_path / "run", iters, "opencl", ckpt_every=10)
    resumed.load_checkpoint()
    assert resumed.step == 10
    w = resumed.terms[0].view_weights
    assert torch.equal(w.prev, at10["photometric"]["view_weights"]["prev"])
    assert not torch.isnan(w.prev).all()  # the weights had state worth restoring
    assert torch.equal(resumed.terms[1].c.detach(), at10["critic"]["c"])
    resumed.train()
    a, b = ref.model.optimizer.params, resumed.model.optimizer.params
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert torch.equal(ref.terms[0].view_weights.prev, resumed.terms[0].view_weights.prev)
    assert torch.equal(ref.terms[1].c, resumed.terms[1].c)
    # The adaptive weights were in play: the reference view's weight was logged.
    assert max(e["view_weight"] for e in ref.log["train"]) > 1.0


def test_scale_regulariser_is_the_mean_volume():
    sc = tiny_scene(backend="opencl")
    m = ScaffoldModel(sc.noisy_points(), None, 1.0, ScaffoldConfig(voxel_size=0.3), seed=0)
    g = torch.Generator().manual_seed(0)
    a = m.n_anchors
    m.optimizer.set_rows("features", torch.randn(a, 32, generator=g))
    m.optimizer.set_rows("offsets", torch.randn(a, 10, 3, generator=g))
    m.optimizer.set_rows("scaling", torch.log(torch.full((a, 6), 0.08)))
    cam = sc.views[0].camera
    out = m.render(cam, 0, backend="opencl")
    dec = m.decode(cam.center_t, m.visible_anchors(cam))
    expected = 0.01 * float(dec["scales"].detach().prod(1).mean())
    term = ScaleVolumeReg()
    ctx = LossContext(view=sc.views[0], index=0, out=out, step=0, model=m)
    assert math.isclose(float(term.weight * term(ctx).detach()), expected, rel_tol=1e-5)
    sc.views[0].weight = 0.0  # a switched-off view gets no regulariser either
    assert float(term(ctx)) == 0.0 and not term(ctx).requires_grad


def _scales_ctx(scales: Tensor, weight: float = 1.0, means2d=None, mask=None) -> LossContext:
    from types import SimpleNamespace

    out = SimpleNamespace(image=torch.zeros(2, 2, 3), meta={"scales": scales, "means2d": means2d})
    view = SimpleNamespace(weight=weight, meta={} if mask is None else {"mask": mask})
    return LossContext(view=view, index=0, out=out, step=0, model=None)


def test_needle_regulariser_in_the_mask_counts_only_the_gaussians_centred_there():
    needle = torch.tensor([[1.0, 0.01, 0.01]] * 4)
    # centres: inside the mask, outside it, off the image left, below it
    means2d = torch.tensor([[2.5, 1.5], [0.5, 0.5], [-3.0, 1.0], [2.0, 9.0]])
    mask = np.zeros((4, 5), bool)
    mask[1:3, 2:4] = True
    term = NeedleReg(max_ratio=4.0, in_mask=True)
    got = term(_scales_ctx(needle, means2d=means2d, mask=mask))
    assert math.isclose(float(got), math.log(25.0), rel_tol=1e-5)  # the mean over the one inside
    sphere_inside = torch.cat([torch.ones(1, 3), needle[1:]])
    assert float(term(_scales_ctx(sphere_inside, means2d=means2d, mask=mask))) == 0.0  # outside ones free
    assert float(term(_scales_ctx(needle, means2d=means2d))) == 0.0  # a view without a mask
    # a culled splat (not drawn) or a NaN centre inside the mask does not count
    culled = _scales_ctx(needle, means2d=means2d, mask=mask)
    culled.out.meta["visible"] = torch.tensor([False, True, True, True])
    assert float(term(culled)) == 0.0
    nan_centre = _scales_ctx(needle, means2d=torch.full((4, 2), float("nan")), mask=mask)
    assert float(term(nan_centre)) == 0.0
    everywhere = NeedleReg(max_ratio=4.0)(_scales_ctx(needle, means2d=means2d, mask=mask))
    assert math.isclose(float(everywhere), math.log(25.0), rel_tol=1e-5)


def test_needle_regulariser_pulls_needles_only():
    """A sphere and a disk (a surface) cost nothing and get no gradient; a needle whose longest
    axis is 100x its middle one costs log(100 / 4) and pulls only those two axes together."""
    log_s = torch.log(torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.01, 1.0], [0.01, 1.0, 0.01]])).requires_grad_(
        True
    )
    term = NeedleReg(max_ratio=4.0)
    value = term(_scales_ctx(log_s.exp()))
    assert math.isclose(float(value.detach()), math.log(25.0) / 3, rel_tol=1e-5)
    (g,) = torch.autograd.grad(value, log_s)
    assert torch.equal(g[:2], torch.zeros(2, 3))  # sphere and disk: untouched
    assert math.isclose(float(g[2, 1]), 1 / 3, rel_tol=1e-5)  # the long axis shrinks
    assert float(g[2, 0]) < 0 or float(g[2, 2]) < 0  # a middle axis grows (topk picks one of the tie)
    assert float(g[2].sum()) == pytest.approx(0.0, abs=1e-7)
    assert float(term(_scales_ctx(log_s.exp(), weight=0.0))) == 0.0  # a switched-off view
    assert float(term(_scales_ctx(torch.zeros(0, 3)))) == 0.0  # nothing drawn
    assert math.isfinite(float(term(_scales_ctx(torch.tensor([[1.0, 0.0, 0.0]])))))  # a degenerate splat


def test_needle_regulariser_minimised_leaves_no_needle():
    """Descending the term alone brings every Gaussian's longest axis within max_ratio of its middle
    one and then stops (zero gradient): the answer is known."""
    g = torch.Generator().manual_seed(0)
    log_s = (torch.randn(200, 3, generator=g) * 2.0).requires_grad_(True)
    term = NeedleReg(max_ratio=3.0)
    opt = torch.optim.SGD([log_s], lr=20.0)
    for _ in range(300):
        opt.zero_grad()
        term(_scales_ctx(log_s.exp())).backward()
        opt.step()
    top2 = log_s.detach().exp().topk(2, dim=1).values
    assert float((top2[:, 0] / top2[:, 1]).max()) <= 3.0 * 1.01
    assert float(term(_scales_ctx(log_s.detach().exp()))) < 1e-3


@pytest.mark.parametrize(
    "kw", [{"max_ratio": 0.5}, {"max_ratio": float("inf")}, {"weight": float("nan")}, {"weight": -1.0}]
)
def test_needle_regulariser_refuses_bad_settings(kw):
    with pytest.raises(ValueError, match="NeedleReg"):
        NeedleReg(**kw)


def test_default_terms_and_unique_names(scene):
    assert [(t.name, t.weight) for t in default_terms("3dgs")] == [("photometric", 1.0)]
    assert [(t.name, t.weight) for t in default_terms("scaffold")] == [
        ("photometric", 1.0), ("scale_reg", 0.01)]  # fmt: skip
    with pytest.raises(ValueError, match="unique"):
        _trainer(scene, [PhotometricLoss(), PhotometricLoss(weight=2.0)])
    np.testing.assert_equal(default_terms("3dgs", LossConfig(lambda_dssim=0.5))[0].cfg.lambda_dssim, 0.5)
