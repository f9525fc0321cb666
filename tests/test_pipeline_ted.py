"""TE-D (coin_cl.pipeline.ted): the adversarial term acts only near the mask, is the plain
fine-tune at lambda_gen = 0, and the stage resumes."""

import numpy as np
import pytest
import torch

from coin_cl.gs.data import View
from coin_cl.gs.gaussians import GaussianConfig
from coin_cl.gs.model_kinds import build_model, scaled_model_config
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.gs.terms import LossContext
from coin_cl.gs.trainer import TrainConfig
from coin_cl.pipeline.ted import RATES, AdversarialTerm, TEDConfig, patch_size, run_ted

W, H = 64, 48


@pytest.fixture(scope="module")
def scene():
    return tiny_scene(n=60, width=W, height=H, n_views=5, backend="opencl")


def _views(scene):
    out = []
    for i, v in enumerate(scene.views):
        mask = np.zeros((H, W), bool)
        if i % 2 == 0:
            mask[16:30, 20:40] = True
        real = (v.image + 0.2 * torch.rand(v.image.shape, generator=torch.Generator().manual_seed(i))).clamp(
            0, 1
        )
        out.append(View(v.camera, v.image, None, 1.0, {"real": real, "mask": mask}))
    return out


def _model(scene):
    return build_model("3dgs", scene.noisy_points(), None, 3.5, seed=0, model_cfg=GaussianConfig())


def test_patch_size_rule():
    assert patch_size(TEDConfig(), 567, 1008) == 64
    assert patch_size(TEDConfig(), 48, 64) == 48
    with pytest.raises(ValueError, match="too small"):
        patch_size(TEDConfig(), 24, 32)


def test_generator_gradient_lives_in_patches_near_the_mask(scene):
    views = _views(scene)
    term = AdversarialTerm(TEDConfig(n_patches=3, margin=4, lambda_gen=1.0))
    img = torch.rand(H, W, 3, requires_grad=True)
    out = type("Out", (), {"image": img})()
    ctx = LossContext(views[0], 0, out, 0, None)
    term(ctx).backward()
    g = img.grad.abs().sum(-1) > 0
    inside = np.zeros((H, W), bool)
    p = term.last["patch"]
    for y, x in term.last["corners"]:
        inside[y : y + p, x : x + p] = True
    assert g.any() and not g.numpy()[~inside].any()
    # every patch centre was drawn from the mask dilated by the margin
    near = np.zeros((H, W), bool)
    near[16 - 4 : 30 + 4, 20 - 4 : 40 + 4] = True
    for y, x in term.last["corners"]:
        cy, cx = min(max(y + p // 2, 0), H - 1), min(max(x + p // 2, 0), W - 1)
        assert inside[cy, cx]
    # a view without a mask contributes exactly nothing
    img.grad = None
    ctx = LossContext(views[1], 1, out, 0, None)
    term(ctx).backward()
    assert not img.grad.any()


def test_discriminator_steps_and_state_round_trips(scene):
    views = _views(scene)
    term = AdversarialTerm(TEDConfig(n_patches=2))
    before = [p.detach().clone() for p in term.disc.parameters()]
    out = type("Out", (), {"image": views[0].image.clone().requires_grad_(True)})()
    ctx = LossContext(views[0], 0, out, 0, None)
    term(ctx)
    term.step_after(ctx)
    assert "disc" in ctx.log and any(not torch.equal(a, b) for a, b in zip(before, term.disc.parameters()))
    other = AdversarialTerm(TEDConfig(n_patches=2, seed=5))
    other.load_state_dict(term.state_dict())
    for a, b in zip(term.disc.state_dict().values(), other.disc.state_dict().values()):
        assert torch.equal(a, b)
    assert term.rng.integers(1 << 30) == other.rng.integers(1 << 30)


def _params(model):
    return {k: v.detach().clone() for k, v in model.optimizer.params.items()}


def test_lambda_gen_zero_is_the_plain_fine_tune(scene, tmp_path):
    views = _views(scene)
    tc = TrainConfig(model="3dgs", progress=False, export_ply=False, ckpt_every=0)
    runs = {}
    for name, lam, adv in (("plain", 0.01, 0), ("zero", 0.0, 6)):
        cfg = TEDConfig(iters_finetune=6 - adv, iters_adversarial=adv, lambda_gen=lam)
        _, model = run_ted(_model(scene), views, [], tmp_path / name, cfg, tc)
        runs[name] = _params(model)
    for k in runs["plain"]:
        assert torch.equal(runs["plain"][k], runs["zero"][k]), k


def test_adversarial_phase_changes_the_result_and_resumes(scene, tmp_path):
    views = _views(scene)
    tc = TrainConfig(model="3dgs", progress=False, export_ply=False, ckpt_every=2)
    cfg = TEDConfig(iters_finetune=2, iters_adversarial=4, lambda_gen=1.0)
    res, full = run_ted(_model(scene), views, [], tmp_path / "full", cfg, tc)
    assert res["adversarial"]["step"] == 4
    plain_cfg = TEDConfig(iters_finetune=2, iters_adversarial=4, lambda_gen=0.0)
    _, plain = run_ted(_model(scene), views, [], tmp_path / "plain", plain_cfg, tc)
    assert any(not torch.equal(a, b) for a, b in zip(_params(full).values(), _params(plain).values()))
    # resume: a finished stage folder reruns as a no-op with the same parameters
    _, again = run_ted(_model(scene), views, [], tmp_path / "full", cfg, tc)
    for k, v in _params(full).items():
        assert torch.equal(v, _params(again)[k]), k


def test_continued_rates_go_on_from_where_the_coarse_schedule_stood(scene, tmp_path):
    views = _views(scene)
    tc = TrainConfig(model="3dgs", progress=False, export_ply=False, ckpt_every=0)
    coarse = scaled_model_config("3dgs", 26)  # one schedule over the coarse stage's 20 + TE-D's 6
    moved = {}
    for rates in RATES:
        start = build_model("3dgs", scene.noisy_points(), None, 3.5, seed=0, model_cfg=coarse)
        before = start.optimizer.params["means"].detach().clone()
        cfg = TEDConfig(iters_finetune=6, iters_adversarial=2, lambda_gen=0.0, rates=rates)
        _, model = run_ted(start, views, [], tmp_path / rates, cfg, tc, steps_before=20)
        # after both phases: continued, the adversarial phase holds the final rate; restarted, its
        # schedule starts again at the initial one
        want = coarse.lr_means(26 if rates == "continue" else 0) * 3.5
        assert model.optimizer.lr("means", 0) == pytest.approx(want, rel=1e-9), rates
        moved[rates] = (model.optimizer.params["means"].detach() - before).abs().mean().item()
    # going on from step 20 of 26 (3% of the initial rate and falling), the positions barely move
    assert 0 < moved["continue"] < 0.2 * moved["restart"]
    with pytest.raises(ValueError, match="TEDConfig.rates is 'warm'"):
        TEDConfig(rates="warm")


def test_discriminator_probe_measures_a_positive_cost_that_grows_with_the_patch():
    from coin_cl.pipeline.ted import TEDConfig, probe_discriminator_seconds

    small = probe_discriminator_seconds(TEDConfig(patch=32, n_patches=1), 48, 48, steps=2)
    large = probe_discriminator_seconds(TEDConfig(patch=64, n_patches=8), 144, 192, steps=2)
    assert np.isfinite(small) and 0 < small < large < 30


def test_needle_term_runs_in_both_phases_when_asked(scene, tmp_path):
    """needle_ratio > 0 adds NeedleReg (inside the masks) to both phases' losses; 0 leaves the
    plain fine-tune bit-exact; ratios below 1 are refused."""
    views = _views(scene)
    tc = TrainConfig(model="3dgs", progress=False, export_ply=False, ckpt_every=0, log_every=1)
    res, _ = run_ted(_model(scene), views, [], tmp_path / "needle",
                     TEDConfig(iters_finetune=2, iters_adversarial=2, needle_ratio=1.5), tc)  # fmt: skip
    for phase in ("finetune", "adversarial"):
        logged = (tmp_path / "needle" / phase / "log.json").read_text()
        assert "needle_reg" in logged, phase
    _, off = run_ted(
        _model(scene), views, [], tmp_path / "off", TEDConfig(iters_finetune=3, iters_adversarial=0), tc
    )
    zero = TEDConfig(iters_finetune=3, iters_adversarial=0, needle_ratio=2.0, needle_weight=0.0)
    _, zero_w = run_ted(_model(scene), views, [], tmp_path / "zero_w", zero, tc)
    for k, v in _params(off).items():
        assert torch.equal(v, _params(zero_w)[k]), k
    for bad in ({"needle_ratio": 0.5}, {"needle_ratio": float("inf")}, {"needle_weight": -1.0}):
        with pytest.raises(ValueError, match=f"TEDConfig.{next(iter(bad))}"):
            TEDConfig(**bad)
