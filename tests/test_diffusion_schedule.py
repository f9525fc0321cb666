"""The SD noise schedule and latent-diffusion's DDIM timestep selection."""

import numpy as np
import pytest
import torch
from coin_cl.diffusion.schedule import ScheduleConfig, alphas_cumprod, ddim_alphas, ddim_sigma, ddim_timesteps


def test_schedule_matches_stable_diffusion():
    acp = alphas_cumprod()
    betas = np.linspace(0.00085**0.5, 0.012**0.5, 1000) ** 2
    np.testing.assert_allclose(acp.numpy(), np.cumprod(1 - betas), rtol=1e-12)
    assert abs(float(acp[-1]) - 0.0047) < 1e-4  # SD's terminal alpha_bar


def test_timesteps_uniform_and_quad():
    u = ddim_timesteps(50, "uniform")
    assert u[0] == 1 and u[-1] == 981 and np.all(np.diff(u) == 20)
    u3 = ddim_timesteps(3, "uniform")
    assert list(u3) == [1, 334, 667]  # S not dividing T: still S steps, all in range
    q = ddim_timesteps(200, "quad")
    assert len(q) == 200 and q[0] == 1 and q[-1] == 801
    assert np.all(np.diff(q) >= 0) and np.diff(q)[-1] > np.diff(q)[10]  # denser near t = 0
    with pytest.raises(ValueError, match="discretization"):
        ddim_timesteps(10, "cosine")


def test_ddim_alphas_and_sigma():
    acp = alphas_cumprod()
    t = ddim_timesteps(50, "uniform")
    a, a_prev = ddim_alphas(t, acp)
    assert float(a_prev[0]) == float(acp[0]) and torch.equal(a_prev[1:], acp[t[:-1]])
    assert torch.all(a_prev > a)
    assert torch.equal(ddim_sigma(a, a_prev, 0.0), torch.zeros(50, dtype=torch.float64))
    # eta = 1 is DDPM's posterior std: sigma^2 = (1 - a_prev)/(1 - a) * (1 - a/a_prev)
    s1 = ddim_sigma(a, a_prev, 1.0)
    assert torch.allclose(s1**2, (1 - a_prev) / (1 - a) * (1 - a / a_prev))
    with pytest.raises(ValueError, match="beta_start"):
        alphas_cumprod(ScheduleConfig(beta_start=0.02, beta_end=0.01))
    with pytest.raises(ValueError, match="out of range"):
        ddim_alphas(np.array([5, 1000]), acp)
