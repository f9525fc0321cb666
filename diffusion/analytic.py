"""An analytic data model with an exact denoiser, for tests and the sampler benchmark.

Data x0 ~ N(mu, diag(s^2)) in D dimensions. With z_t = sqrt(a) x0 + sqrt(1-a) eps, z_t is Gaussian with
mean sqrt(a) mu and variance a s^2 + 1 - a, and the exact (MMSE) predictors are linear in z_t:
    E[eps | z_t] = sqrt(1-a) (z_t - sqrt(a) mu) / (a s^2 + 1 - a)
    E[x0  | z_t] = (z_t - sqrt(1-a) E[eps | z_t]) / sqrt(a)
    E[v   | z_t] = sqrt(a) E[eps | z_t] - sqrt(1-a) E[x0 | z_t]
so DDIM with this denoiser integrates the exact probability-flow ODE up to discretisation error.
"""

from __future__ import annotations

from typing import Any

import torch

from .sampling import Denoiser
from .schedule import ScheduleConfig, alphas_cumprod


class GaussianDenoiser(Denoiser):
    """Exact eps- or v-predictor of N(mu, diag(std^2)).

    mu, std: (D,) tensors (float64 recommended). Latents are (B, D).
    """

    name = "analytic Gaussian"

    def __init__(
        self,
        mu: torch.Tensor,
        std: torch.Tensor,
        prediction_type: str = "eps",
        schedule: ScheduleConfig | None = None,
    ) -> None:
        if mu.shape != std.shape or mu.dim() != 1:
            raise ValueError(f"mu and std must both be (D,), got {tuple(mu.shape)} and {tuple(std.shape)}")
        if prediction_type not in ("eps", "v"):
            raise ValueError(f"prediction_type must be 'eps' or 'v', got {prediction_type!r}")
        self.mu, self.std = mu, std
        self.prediction_type = prediction_type
        self.acp = alphas_cumprod(schedule)

    def predict(self, z: torch.Tensor, t: torch.Tensor, cond: Any = None) -> torch.Tensor:
        a = self.acp[t].to(z.dtype).unsqueeze(1)
        mu, var = self.mu.to(z.dtype), self.std.to(z.dtype) ** 2
        eps = (1 - a).sqrt() * (z - a.sqrt() * mu) / (a * var + 1 - a)
        if self.prediction_type == "eps":
            return eps
        x0 = (z - (1 - a).sqrt() * eps) / a.sqrt()
        return a.sqrt() * eps - (1 - a).sqrt() * x0

    def marginal(self, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std of z_t, two (D,) tensors: the exact start for a DDIM run that begins at t."""
        a = self.acp[t].to(self.mu.dtype)
        return a.sqrt() * self.mu, (a * self.std**2 + 1 - a).sqrt()

    def sample_moments(self, sampler: Any, use_x0: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact mean and std of a deterministic (eta = 0, unguided) sampler's output, two (D,) tensors.

        The denoiser is linear, so the whole DDIM map is affine per dimension: running it on the
        marginal's mean and on mean + std gives the output mean and std without Monte-Carlo noise.
        """
        m, s = self.marginal(int(sampler.timesteps[-1]))
        z = torch.stack([m, m + s]).to(self.mu.dtype)
        r = sampler.sample(z)
        out = r.x0 if use_x0 else r.z
        return out[0], (out[1] - out[0]).abs()
