"""The DDPM noise schedule of Stable Diffusion and DDIM step selection.

Conventions (as in latent-diffusion / Stable Diffusion):
- ``alphas_cumprod[t]`` (written alpha_bar_t) for t = 0..T-1, T = 1000 training steps, from the
  "scaled-linear" betas: beta_t = (linspace(sqrt(0.00085), sqrt(0.012), T)[t])^2.
- A noisy sample is z_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) eps.
- DDIM timestep selection as latent-diffusion's ``make_ddim_timesteps``: 'uniform' takes every
  (T // S)-th step, 'quad' takes floor(linspace(0, sqrt(0.8 T), S)^2); both add one so the first
  (least noisy) step is 1 and alpha_bar_prev of the last step is alpha_bar_0.

'quad' with many steps repeats small timesteps (e.g. S=200 gives several zeros before the +1); that is
latent-diffusion's definition and the repeated steps are identity steps (alpha_bar_prev == alpha_bar).
We keep it unchanged so the step counts mean what they mean in the paper's configuration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class ScheduleConfig:
    """The training noise schedule.

    num_train_steps: T, number of DDPM training steps (SD: 1000).
    beta_start, beta_end: first and last beta of the scaled-linear schedule (SD: 0.00085, 0.012).
    """

    num_train_steps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012


def alphas_cumprod(cfg: ScheduleConfig | None = None) -> torch.Tensor:
    """alpha_bar_t of the scaled-linear schedule: float64 tensor of shape (T,), decreasing from ~1."""
    cfg = cfg or ScheduleConfig()
    if cfg.num_train_steps < 2:
        raise ValueError(f"num_train_steps must be >= 2, got {cfg.num_train_steps}")
    if not (0.0 < cfg.beta_start < cfg.beta_end < 1.0):
        raise ValueError(f"need 0 < beta_start < beta_end < 1, got {cfg.beta_start}, {cfg.beta_end}")
    b0, b1 = cfg.beta_start**0.5, cfg.beta_end**0.5
    betas = torch.linspace(b0, b1, cfg.num_train_steps, dtype=torch.float64) ** 2
    return torch.cumprod(1.0 - betas, dim=0)


def ddim_timesteps(
    num_steps: int, discretization: str = "uniform", num_train_steps: int = 1000
) -> np.ndarray:
    """DDIM timesteps in increasing order, int64 array of shape (num_steps,), as latent-diffusion.

    discretization: 'uniform' (every T//S-th step) or 'quad' (quadratically spaced up to 0.8 T, denser
    near t=0). The values include latent-diffusion's +1 shift.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if discretization == "uniform":
        if num_steps > num_train_steps:
            raise ValueError(f"uniform: num_steps {num_steps} > num_train_steps {num_train_steps}")
        c = num_train_steps // num_steps
        # latent-diffusion's range() yields one extra step when S does not divide T (and then indexes
        # past the end); keeping the first S is the same for divisors and valid otherwise
        steps = np.asarray(list(range(0, num_train_steps, c)))[:num_steps]
    elif discretization == "quad":
        steps = ((np.linspace(0, np.sqrt(num_train_steps * 0.8), num_steps)) ** 2).astype(int)
    else:
        raise ValueError(f"discretization must be 'uniform' or 'quad', got {discretization!r}")
    return (steps + 1).astype(np.int64)


def ddim_alphas(timesteps: np.ndarray, acp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(alpha_bar[t_i], alpha_bar_prev[t_i]) for increasing DDIM timesteps: two float64 tensors (S,).

    alpha_bar_prev of the first (least noisy) step is alpha_bar[0], as latent-diffusion.
    """
    t = torch.as_tensor(timesteps, dtype=torch.long)
    if int(t.max()) >= acp.numel() or int(t.min()) < 0:
        raise ValueError(f"timesteps out of range [0, {acp.numel()}): {timesteps}")
    a = acp[t]
    a_prev = torch.cat([acp[:1], acp[t[:-1]]])
    return a, a_prev


def ddim_sigma(a: torch.Tensor, a_prev: torch.Tensor, eta: float) -> torch.Tensor:
    """DDIM noise level sigma_t(eta) = eta sqrt((1-a_prev)/(1-a)) sqrt(1 - a/a_prev); same shape as a."""
    return eta * torch.sqrt((1 - a_prev) / (1 - a) * (1 - a / a_prev))
