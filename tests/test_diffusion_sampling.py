"""DDIM sampler and energy guidance on the analytic Gaussian model (exact denoiser, known answer)."""

import pytest
import torch
from coin_cl.diffusion.analytic import GaussianDenoiser
from coin_cl.diffusion.sampling import DDIMSampler, FunctionDenoiser, SamplerConfig

MU = torch.tensor([1.0, -0.5, 0.3, 2.0], dtype=torch.float64)
STD = torch.tensor([0.5, 1.0, 1.5, 0.8], dtype=torch.float64)


@pytest.mark.parametrize("disc", ["uniform", "quad"])
def test_ddim_converges_to_true_moments(disc):
    errs = []
    for steps in (10, 50, 200):
        s = DDIMSampler(GaussianDenoiser(MU, STD), SamplerConfig(num_steps=steps, discretization=disc))
        m, sd = s.denoiser.sample_moments(s)
        errs.append(float((sd - STD).abs().max()))
        assert torch.allclose(m, MU, atol=1e-9)
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 0.012 and errs[0] / errs[2] > 10  # first order in the step count


def test_ddim_stochastic_eta_matches_moments():
    s = DDIMSampler(GaussianDenoiser(MU, STD), SamplerConfig(num_steps=100, eta=1.0))
    g = torch.Generator().manual_seed(0)
    m0, s0 = s.denoiser.marginal(int(s.timesteps[-1]))
    z = m0 + s0 * torch.randn(4000, 4, generator=g, dtype=torch.float64)
    x = s.sample(z, generator=g).x0
    assert (x.mean(0) - MU).abs().max() < 0.08
    cov = torch.cov(x.T)
    assert (cov.diagonal().sqrt() - STD).abs().max() < 0.08
    assert (cov - torch.diag(cov.diagonal())).abs().max() < 0.08  # independent dimensions stay so


@pytest.mark.parametrize("disc", ["uniform", "quad"])
def test_eps_and_v_prediction_agree(disc):
    z = torch.randn(8, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    outs = []
    for pt in ("eps", "v"):
        cfg = SamplerConfig(num_steps=30, discretization=disc, eta=0.5)
        s = DDIMSampler(GaussianDenoiser(MU, STD, pt), cfg)
        outs.append(s.sample(z, generator=torch.Generator().manual_seed(2)).z)
    assert torch.allclose(outs[0], outs[1], atol=1e-10)


def test_classifier_free_guidance_combines_linearly():
    # cond -> exact model of MU, uncond -> exact model of 0: s = 1 is the conditional model alone and
    # the combination is u + s (c - u) of the two predictions.
    gc, gu = GaussianDenoiser(MU, STD), GaussianDenoiser(torch.zeros(4, dtype=torch.float64), STD)
    fn = FunctionDenoiser(lambda z, t, c: (gc if c == "c" else gu).predict(z, t))
    z = torch.randn(3, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    s1 = DDIMSampler(fn, SamplerConfig(num_steps=20, cfg_scale=1.0)).sample(z, "c", "u").z
    ref = DDIMSampler(gc, SamplerConfig(num_steps=20)).sample(z).z
    assert torch.equal(s1, ref)
    s3 = DDIMSampler(fn, SamplerConfig(num_steps=1, cfg_scale=3.0))
    t = torch.full((3,), int(s3.timesteps[0]))
    out = s3._model(z, int(s3.timesteps[0]), "c", "u")
    assert torch.allclose(out, gu.predict(z, t) + 3.0 * (gc.predict(z, t) - gu.predict(z, t)))


def _guided(energy, **kw):
    cfg = SamplerConfig(num_steps=50, eta=0.0, **kw)
    s = DDIMSampler(GaussianDenoiser(MU, STD), cfg)
    m0, s0 = s.denoiser.marginal(int(s.timesteps[-1]))
    z = m0 + s0 * torch.randn(2000, 4, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    return s.sample(z, energy=energy, generator=torch.Generator().manual_seed(5))


def test_guidance_moves_toward_quadratic_target():
    target = torch.tensor([-1.0, 1.0, 1.0, 0.0], dtype=torch.float64)

    def energy(x0):
        return 0.5 * ((x0 - target) ** 2).sum()

    base_x0 = _guided(None).x0
    base = base_x0.mean(0)
    d0 = (base - target).norm()
    prev = d0
    for c in (0.1, 0.5):
        r = _guided(energy, guidance_scale=c)
        m = r.x0.mean(0)
        d = (m - target).norm()
        assert d < prev, (c, float(d), float(prev))  # stronger guidance, closer to the target
        prev = d
        shift = m - base
        # the mean moves along the energy's descent direction (the exact posterior mean of a Gaussian
        # prior times exp(-E) lies on the segment between MU and the target, weighted by STD^2)
        post = (MU / STD**2 + target) / (1 / STD**2 + 1)
        cos = torch.dot(shift, post - MU) / (shift.norm() * (post - MU).norm())
        assert cos > 0.9
        assert len(r.energies) == 50 and r.energies[-1] < float(energy(base_x0))
    assert prev < 0.85 * d0


def test_zero_energy_is_bit_identical():
    cfg = SamplerConfig(num_steps=25, eta=0.7, guidance_scale=0.5)
    s = DDIMSampler(GaussianDenoiser(MU, STD), cfg)
    z = torch.randn(16, 4, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    plain = s.sample(z, generator=torch.Generator().manual_seed(7)).z
    zero_const = s.sample(z, energy=lambda x: torch.zeros(()), generator=torch.Generator().manual_seed(7)).z
    zero_grad = s.sample(z, energy=lambda x: 0.0 * x.sum(), generator=torch.Generator().manual_seed(7)).z
    assert torch.equal(plain, zero_const) and torch.equal(plain, zero_grad)


def test_time_travel_one_repeat_is_plain_step():
    def energy(x0):
        return ((x0 - 3.0) ** 2).sum()

    a = _guided(energy, guidance_scale=0.2, travel_repeats=1, travel_start=0.0, travel_end=1.0).z
    b = _guided(energy, guidance_scale=0.2, travel_start=0.0, travel_end=0.0).z
    c = _guided(energy, guidance_scale=0.2, travel_repeats=3, travel_start=0.2, travel_end=0.5).z
    assert torch.equal(a, b)
    assert not torch.equal(a, c) and torch.isfinite(c).all()
    # more repeats = more guided updates: closer to the energy's minimum
    assert (c.mean(0) - 3.0).norm() < (a.mean(0) - 3.0).norm()


def test_bad_config_and_input():
    with pytest.raises(ValueError, match="window"):
        DDIMSampler(GaussianDenoiser(MU, STD), SamplerConfig(guidance_start=0.8, guidance_end=0.2))
    with pytest.raises(ValueError, match="travel_repeats"):
        DDIMSampler(GaussianDenoiser(MU, STD), SamplerConfig(travel_repeats=0))
    s = DDIMSampler(GaussianDenoiser(MU, STD), SamplerConfig(num_steps=5))
    with pytest.raises(ValueError, match="NaN"):
        s.sample(torch.full((1, 4), float("nan"), dtype=torch.float64))
