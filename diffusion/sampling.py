"""DDIM sampling with classifier-free guidance and FreeDoM-style energy guidance.

The sampler talks to any model through :class:`Denoiser` (an eps- or v-predictor with optional
encode/decode), so Stable Diffusion 2 inpainting (:mod:`.sd2`), the embedded scene prior
(:mod:`.scene_prior`) and the analytic Gaussian model (:mod:`.analytic`) all plug in.

One DDIM step from z_t (alpha_bar a) to z_prev (alpha_bar a_prev), as latent-diffusion's sampler:
    x0   = (z_t - sqrt(1-a) eps) / sqrt(a)            (eps-prediction)
    x0   = sqrt(a) z_t - sqrt(1-a) v,  eps = sqrt(a) v + sqrt(1-a) z_t   (v-prediction)
    z_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev - sigma^2) eps + sigma * noise

Energy guidance (FreeDoM, Yu et al. 2023): with z_t requiring grad, the energy E is evaluated on the
decoded x0 prediction, g = dE/dz_t flows back through the decoder AND the denoiser, and the step becomes
    z_prev <- z_prev - rho g,   rho = c * rms(z_prev - z_t) / rms(g)      (per sample)
so c is a fraction of the size of the plain DDIM update, independent of the energy's scale. Guidance
runs only inside a window of the trajectory; inside a (sub-)window each step is repeated
``travel_repeats`` times ("time travel"): after a guided step z_prev is re-noised back to level t with
the schedule's ratio, z_t = sqrt(a/a_prev) z_prev + sqrt(1 - a/a_prev) n, and the step redone.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from .schedule import ScheduleConfig, alphas_cumprod, ddim_alphas, ddim_sigma, ddim_timesteps

log = logging.getLogger(__name__)

EnergyFn = Callable[[torch.Tensor], torch.Tensor]


class Denoiser:
    """Abstract denoiser: predicts eps or v from a noisy latent.

    Subclasses set ``prediction_type`` ('eps' or 'v') and implement :meth:`predict`. ``encode`` maps an
    image to the sampler's latent space and ``decode`` back (identity by default, for pixel-space
    models); ``decode`` must be differentiable for energy guidance.
    """

    prediction_type: str = "eps"
    name: str = "denoiser"

    def predict(self, z: torch.Tensor, t: torch.Tensor, cond: Any = None) -> torch.Tensor:
        """Model output for latents z (B, C, ...) at integer timesteps t (B,) int64; same shape as z."""
        raise NotImplementedError

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Image (B, 3, H, W) in [0, 1] -> latent. Identity here."""
        return x

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent -> image (B, 3, H, W) in [0, 1] (differentiable). Identity here."""
        return z


class FunctionDenoiser(Denoiser):
    """A :class:`Denoiser` around a plain callable ``fn(z, t, cond) -> eps or v``."""

    def __init__(
        self,
        fn: Callable[[torch.Tensor, torch.Tensor, Any], torch.Tensor],
        prediction_type: str = "eps",
        decode: Callable[[torch.Tensor], torch.Tensor] | None = None,
        name: str = "function",
    ) -> None:
        if prediction_type not in ("eps", "v"):
            raise ValueError(f"prediction_type must be 'eps' or 'v', got {prediction_type!r}")
        self.fn = fn
        self.prediction_type = prediction_type
        self._decode = decode
        self.name = name

    def predict(self, z: torch.Tensor, t: torch.Tensor, cond: Any = None) -> torch.Tensor:
        return self.fn(z, t, cond)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return z if self._decode is None else self._decode(z)


@dataclass
class SamplerConfig:
    """Every constant of the sampler.

    num_steps: DDIM steps (paper: 50 for the initial inpainting, 200 for CLG).
    discretization: 'uniform' (initial inpainting) or 'quad' (CLG), latent-diffusion's definitions.
    eta: DDIM stochasticity; 0 = deterministic DDIM, 1 = DDPM-like ancestral noise.
    cfg_scale: classifier-free guidance scale s, out = u + s (c - u); 1 disables it (one model call).
    guidance_scale: FreeDoM's c in rho = c rms(correction)/rms(grad); 0 disables energy guidance.
    guidance_start, guidance_end: the guidance window as fractions of the trajectory, step k of S is
        guided when start <= k/S < end (k = 0 is the first, noisiest step).
    travel_repeats: time-travel repeats per guided step inside the travel window; 1 = plain step.
    travel_start, travel_end: the time-travel sub-window, same units as the guidance window
        (FreeDoM repeats in the early-middle part of the trajectory, where layout is decided).
    schedule: the training noise schedule.
    """

    num_steps: int = 50
    discretization: str = "uniform"
    eta: float = 0.0
    cfg_scale: float = 1.0
    guidance_scale: float = 0.0
    guidance_start: float = 0.0
    guidance_end: float = 1.0
    travel_repeats: int = 1
    travel_start: float = 0.2
    travel_end: float = 0.5
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)

    def validate(self) -> None:
        if self.num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {self.num_steps}")
        if self.eta < 0:
            raise ValueError(f"eta must be >= 0, got {self.eta}")
        if self.travel_repeats < 1:
            raise ValueError(f"travel_repeats must be >= 1 (1 = no time travel), got {self.travel_repeats}")
        for a, b, what in (
            (self.guidance_start, self.guidance_end, "guidance"),
            (self.travel_start, self.travel_end, "travel"),
        ):
            if not (0.0 <= a <= 1.0 and 0.0 <= b <= 1.0 and a <= b):
                raise ValueError(f"{what} window must satisfy 0 <= start <= end <= 1, got ({a}, {b})")


@dataclass
class SampleResult:
    """z: final latent (as latent-diffusion, at alpha_bar_0); x0: the last step's x0 prediction;
    energies: energy at each guided step (mean over repeats), [] when unguided."""

    z: torch.Tensor
    x0: torch.Tensor
    energies: list[float]


def split_prediction(
    out: torch.Tensor, z: torch.Tensor, a: float, prediction_type: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """(x0, eps) from a model output at alpha_bar a; tensors of z's shape and dtype."""
    sa, s1a = math.sqrt(a), math.sqrt(1.0 - a)
    if prediction_type == "eps":
        return (z - s1a * out) / sa, out
    if prediction_type == "v":
        return sa * z - s1a * out, sa * out + s1a * z
    raise ValueError(f"prediction_type must be 'eps' or 'v', got {prediction_type!r}")


def _rms(x: torch.Tensor) -> torch.Tensor:
    """Per-sample root mean square, shape (B, 1, ..., 1) for broadcasting."""
    dims = tuple(range(1, x.dim()))
    return x.pow(2).mean(dim=dims, keepdim=True).sqrt()


class DDIMSampler:
    """DDIM with CFG, FreeDoM energy guidance and time travel (see the module docstring)."""

    def __init__(self, denoiser: Denoiser, cfg: SamplerConfig | None = None) -> None:
        self.denoiser = denoiser
        self.cfg = cfg or SamplerConfig()
        self.cfg.validate()
        acp = alphas_cumprod(self.cfg.schedule)
        self.timesteps = ddim_timesteps(
            self.cfg.num_steps, self.cfg.discretization, self.cfg.schedule.num_train_steps
        )
        a, a_prev = ddim_alphas(self.timesteps, acp)
        self.a = a.tolist()
        self.a_prev = a_prev.tolist()
        self.sigma = ddim_sigma(a, a_prev, self.cfg.eta).tolist()

    def _model(self, z: torch.Tensor, t: int, cond: Any, uncond: Any) -> torch.Tensor:
        tt = torch.full((z.shape[0],), t, dtype=torch.long)
        out = self.denoiser.predict(z, tt, cond)
        if self.cfg.cfg_scale != 1.0 and uncond is not None:
            out_u = self.denoiser.predict(z, tt, uncond)
            out = out_u + self.cfg.cfg_scale * (out - out_u)
        return out

    def step(
        self,
        z: torch.Tensor,
        i: int,
        cond: Any = None,
        uncond: Any = None,
        energy: EnergyFn | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, float | None]:
        """One DDIM step at index i of ``self.timesteps`` (increasing order), guided when energy is given.

        z: (B, C, ...) latent at level timesteps[i]. Returns (z_prev, x0, energy value or None);
        z_prev and x0 have z's shape and dtype and carry no autograd graph.
        """
        a, a_prev, sigma = self.a[i], self.a_prev[i], self.sigma[i]
        t = int(self.timesteps[i])
        pt = self.denoiser.prediction_type
        grad = None
        e_val = None
        if energy is not None and self.cfg.guidance_scale != 0.0:
            z_in = z.detach().requires_grad_(True)
            with torch.enable_grad():
                x0, eps = split_prediction(self._model(z_in, t, cond, uncond), z_in, a, pt)
                e = energy(self.denoiser.decode(x0))
                if e.dim() > 0:
                    e = e.sum()
                if e.requires_grad:
                    (grad,) = torch.autograd.grad(e, z_in)
            e_val = float(e.detach())
            x0, eps = x0.detach(), eps.detach()
        else:
            with torch.no_grad():
                x0, eps = split_prediction(self._model(z, t, cond, uncond), z, a, pt)
        z_prev = math.sqrt(a_prev) * x0 + math.sqrt(max(1.0 - a_prev - sigma**2, 0.0)) * eps
        if sigma > 0:
            z_prev = z_prev + sigma * torch.randn(z.shape, generator=generator, dtype=z.dtype)
        if grad is not None and bool((grad != 0).any()):
            g_rms = _rms(grad)
            # rho scales the energy step to a fraction c of the DDIM update itself (FreeDoM); a sample
            # whose gradient is exactly zero gets no step (and no 0/0).
            rho = self.cfg.guidance_scale * _rms(z_prev - z) / torch.where(g_rms > 0, g_rms, 1.0)
            z_prev = z_prev - torch.where(g_rms > 0, rho, 0.0) * grad
        return z_prev, x0, e_val

    def noised(self, x0: torch.Tensor, start: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """The clean latent x0 (B, C, ...) forward-noised to the level of step `start` (the z_T of
        `sample(..., start=start)`): sqrt(a) x0 + sqrt(1 - a) eps."""
        a = self.a[len(self.timesteps) - 1 - start]
        eps = torch.randn(x0.shape, generator=generator, dtype=x0.dtype)
        return math.sqrt(a) * x0 + math.sqrt(1.0 - a) * eps

    def _in(self, k: int, start: float, end: float) -> bool:
        f = k / self.cfg.num_steps
        return start <= f < end

    def sample(
        self,
        z_T: torch.Tensor,
        cond: Any = None,
        uncond: Any = None,
        energy: EnergyFn | None = None,
        generator: torch.Generator | None = None,
        callback: Callable[[int, int, torch.Tensor, torch.Tensor], None] | None = None,
        start: int = 0,
    ) -> SampleResult:
        """Run the whole trajectory from z_T (B, C, ...) (pure noise, any float dtype).

        start: skip the first `start` steps (SDEdit): z_T is then a latent at level
        `self.timesteps[S - 1 - start]` (`noised` makes one from a clean latent); the guidance and
        time-travel windows keep their place in the whole trajectory.

        energy: maps the decoded x0 prediction (B, 3, H, W) to a scalar (or per-sample (B,)) energy;
        used only inside the guidance window. callback(k, t, z_prev, x0) is called after each step
        (k = 0 is the noisiest). Randomness (eta > 0, time travel) comes from ``generator``.
        """
        if not torch.isfinite(z_T).all():
            raise ValueError("z_T contains NaN or Inf")
        c = self.cfg
        z = z_T
        x0 = z_T
        energies: list[float] = []
        S = len(self.timesteps)
        if not 0 <= start < S:
            raise ValueError(f"start must be in [0, {S}), got {start}")
        for k in range(start, S):
            i = S - 1 - k
            guided = (
                energy is not None
                and c.guidance_scale != 0.0
                and self._in(k, c.guidance_start, c.guidance_end)
            )
            repeats = c.travel_repeats if guided and self._in(k, c.travel_start, c.travel_end) else 1
            e_sum, e_n = 0.0, 0
            for r in range(repeats):
                z_prev, x0, e = self.step(z, i, cond, uncond, energy if guided else None, generator)
                if e is not None:
                    e_sum, e_n = e_sum + e, e_n + 1
                if r < repeats - 1:
                    # time travel: back to level t with the schedule's ratio, then redo the step
                    ratio = self.a[i] / self.a_prev[i]
                    n = torch.randn(z.shape, generator=generator, dtype=z.dtype)
                    z = math.sqrt(ratio) * z_prev + math.sqrt(max(1.0 - ratio, 0.0)) * n
            z = z_prev
            if e_n:
                energies.append(e_sum / e_n)
            if callback is not None:
                callback(k, int(self.timesteps[i]), z, x0)
        return SampleResult(z=z, x0=x0, energies=energies)
