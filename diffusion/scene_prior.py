"""The "scene prior": a small inpainting diffusion model trained on the scene's own images.

It is the embedded default when no Stable Diffusion weights exist, so the initial inpainting and the
consistency-guided sampling (CLG) run for real on any machine. It is always called "scene prior" in
logs and results; it is not Stable Diffusion and makes no claim to its quality.

Model: a plain-torch UNet (3 resolutions, GroupNorm + SiLU residual blocks, sinusoidal time embedding;
1.5 M parameters at the default base 32, 3.4 M at 48; base 32 because a training step of 16 64x64
patches takes 0.7 s on 2 cores against 1.4 s at 48) in pixel space ([-1, 1]), input 7 channels =
[z_t (3), masked image (3, 0 in the hole), hole mask (1)], output v (or eps) for the SD schedule of
:mod:`.schedule`, so the sampler of :mod:`.sampling` drives it exactly as it drives SD2 (including
energy guidance).

Training data: random square patches of the scene's images at a few scales (side P s for
s in ``scales``, area-averaged down to P so the model also works on crops larger than P); synthetic
holes (rectangles, ellipses, thick strokes) are placed only where pixels are known, never inside the
excluded (object) masks; excluded pixels inside a patch are part of the conditioning hole and carry no
loss. A fixed step count (`train_steps`; the pipeline's choice) or a wall-clock budget; training
checkpoints every minute and resumes after a kill; the result is cached by a hash of the images,
the excluded masks and the settings (written atomically), so a second run reuses it.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from coin_cl.atomic import atomic_write  # pure stdlib: no engine, no OpenCL
from coin_cl.checkpoint import load_checkpoint, malformed  # torch only: no engine, no OpenCL
from coin_cl.timing import median_step_seconds  # pure stdlib too

from .sampling import DDIMSampler, Denoiser, EnergyFn, SamplerConfig, split_prediction
from .schedule import ScheduleConfig, alphas_cumprod

log = logging.getLogger(__name__)
NAME = "scene prior"
_VERSION = 1  # bump when the model or the training changes, so old caches are not reused
# Optimizer steps per second of the default prior (base 32, batch 16 of 64x64 patches) on the
# project's 2-core machine kind: 133 steps in 120 s (docs/BENCHMARKS.md, "Diffusion").
STEPS_PER_SECOND = 133 / 120
# Wall-clock seconds between training checkpoints, so that a kill loses at most about this much
# ($COIN_CKPT_SECONDS overrides it, as for the GS trainer: benchmarks/faults.py uses 1).
CKPT_SECONDS = float(os.environ.get("COIN_CKPT_SECONDS", 60.0))
# What to do with a cached prior or its training checkpoint that cannot be read (ends the one line).
CACHE_REMEDY = "delete it: the scene prior is trained again"


def steps_for_seconds(seconds: float, seconds_per_step: float | None = None) -> int:
    """The step count that takes about `seconds` (at least 1): at `seconds_per_step` where measured
    on this machine (`probe_seconds_per_step`), else at the 2-core rate `STEPS_PER_SECOND`."""
    if seconds_per_step is None:
        return max(1, round(seconds * STEPS_PER_SECOND))
    if not math.isfinite(seconds_per_step) or seconds_per_step <= 0:
        raise ValueError(f"scene prior seconds per step must be a positive number, got {seconds_per_step}")
    return max(1, round(seconds / seconds_per_step))


def probe_seconds_per_step(cfg: ScenePriorConfig | None = None, steps: int = 3, warmup: int = 1) -> float:
    """Seconds one training step of the prior `cfg` takes on this machine: `warmup` + `steps`
    optimizer steps on random patches of its size and batch (a step's cost depends on the network,
    the patch and the batch, not on the pixels), the median of the timed ones (every fixed stage's
    estimate is scaled by it, `stage_costs.machine_factor`: one slow step must not move them). The
    plan turns the prior's seconds into steps with it (STEPS_PER_SECOND was measured on one
    machine; a slower one ran 1.5x over its share)."""
    cfg = cfg or ScenePriorConfig()
    g = torch.Generator().manual_seed(0)
    net = InpaintUNet(cfg.base)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=0.0)
    acp = alphas_cumprod(cfg.schedule)
    shape = (cfg.batch, 3, cfg.patch, cfg.patch)
    x0 = torch.rand(shape, generator=g) * 2 - 1
    hole = (torch.rand((cfg.batch, 1, cfg.patch, cfg.patch), generator=g) < 0.3).float()
    w = 1 + (cfg.hole_weight - 1) * hole

    def step() -> None:
        t = torch.randint(1, cfg.schedule.num_train_steps, (cfg.batch,), generator=g)
        loss = denoising_loss(net, x0, hole, w, t, torch.randn(shape, generator=g), acp, cfg.prediction_type)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()

    return median_step_seconds(step, steps, warmup)


@dataclass
class ScenePriorConfig:
    """Settings of the scene prior (all part of the cache key); each field says what it means where
    it is declared. Values are checked here: a bad one is an error naming the field."""

    # P, the working size in pixels (square patches and inpainting crops; a multiple of 4, >= 8).
    patch: int = 64
    # Channels at full resolution (a multiple of 8, for GroupNorm); the 3 levels have (1, 2, 4) x base.
    base: int = 32
    # Patch scales s (a P s crop area-averaged to P; each >= 1), so the prior also fills larger holes.
    scales: tuple[int, ...] = (1, 2, 4)
    # Patches per optimizer step (>= 1).
    batch: int = 16
    # AdamW learning rate (> 0; constant: the budget is in seconds).
    lr: float = 1e-3
    # Seconds of wall-clock training when `train_steps` is None (>= 0). In a CoIn run the run sets it
    # (`CoInConfig.prior_seconds`) and converts it to `train_steps`.
    train_seconds: float = 300.0
    # Optimizer steps to train (>= 0; the pipeline's setting: a fixed count gives the same model on
    # any machine and lets a killed run resume to exactly the model it would have made). None: train
    # for `train_seconds` (a resumed run then differs); `steps_for_seconds` converts a time budget
    # at the measured 2-core rate.
    train_steps: int | None = None
    # Optional cap on optimizer steps in either mode (>= 0; tests). None: no cap.
    max_steps: int | None = None
    # Loss weight inside the synthetic hole (>= 0; outside: 1), since the hole is what it must do.
    hole_weight: float = 4.0
    # "v" (default: better conditioned than eps at high noise for a small pixel-space model) or "eps".
    prediction_type: str = "v"
    # RNG seed for init and sampling of patches/holes. In a CoIn run the run's seed.
    seed: int = 0
    # The training noise schedule.
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)

    def __post_init__(self) -> None:
        def whole(x: object, low: int) -> bool:
            return isinstance(x, int) and not isinstance(x, bool) and x >= low

        for name, ok, what in (
            ("patch", whole(self.patch, 8) and self.patch % 4 == 0, "a multiple of 4, >= 8"),
            ("base", whole(self.base, 8) and self.base % 8 == 0, "a multiple of 8, >= 8"),
            ("scales", len(self.scales) > 0 and all(whole(x, 1) for x in self.scales), "integers >= 1"),
            ("batch", whole(self.batch, 1), "an integer >= 1"),
            ("lr", self.lr > 0, "> 0"),
            ("train_seconds", self.train_seconds >= 0, ">= 0"),
            (
                "train_steps",
                self.train_steps is None or whole(self.train_steps, 0),
                "an integer >= 0 or None",
            ),
            ("max_steps", self.max_steps is None or whole(self.max_steps, 0), "an integer >= 0 or None"),
            ("hole_weight", self.hole_weight >= 0, ">= 0"),
            ("prediction_type", self.prediction_type in ("v", "eps"), "'v' or 'eps'"),
        ):
            if not ok:
                raise ValueError(f"ScenePriorConfig.{name} is {getattr(self, name)!r}: give {what}")


def _timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half)
    a = t.float()[:, None] * freqs[None]
    return torch.cat([a.sin(), a.cos()], dim=1)


class _Res(nn.Module):
    def __init__(self, cin: int, cout: int, tdim: int) -> None:
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(8, cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.t = nn.Linear(tdim, cout)
        self.n2, self.c2 = nn.GroupNorm(8, cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        h = self.c1(F.silu(self.n1(x))) + self.t(temb)[:, :, None, None]
        h = self.c2(F.silu(self.n2(h)))
        return self.skip(x) + h


class InpaintUNet(nn.Module):
    """Small inpainting UNet: (z (B,3,H,W), masked (B,3,H,W), hole (B,1,H,W), t (B,)) -> (B,3,H,W).

    H and W must be multiples of 4. Two residual blocks per level, a dilated middle block for context.
    """

    def __init__(self, base: int = 32) -> None:
        super().__init__()
        if base % 8:
            raise ValueError(f"base must be a multiple of 8 (GroupNorm), got {base}")
        c1, c2, c3 = base, 2 * base, 4 * base
        td = 4 * base
        self.tdim = base
        self.temb = nn.Sequential(nn.Linear(base, td), nn.SiLU(), nn.Linear(td, td))
        self.inp = nn.Conv2d(7, c1, 3, padding=1)
        self.d1a, self.d1b = _Res(c1, c1, td), _Res(c1, c1, td)
        self.down1 = nn.Conv2d(c1, c2, 3, stride=2, padding=1)
        self.d2a, self.d2b = _Res(c2, c2, td), _Res(c2, c2, td)
        self.down2 = nn.Conv2d(c2, c3, 3, stride=2, padding=1)
        self.m1, self.m2 = _Res(c3, c3, td), _Res(c3, c3, td)
        self.mid_dil = nn.Conv2d(c3, c3, 3, padding=4, dilation=4)  # wide context at the coarsest level
        self.up2 = nn.ConvTranspose2d(c3, c2, 4, stride=2, padding=1)
        self.u2a, self.u2b = _Res(2 * c2, c2, td), _Res(c2, c2, td)
        self.up1 = nn.ConvTranspose2d(c2, c1, 4, stride=2, padding=1)
        self.u1a, self.u1b = _Res(2 * c1, c1, td), _Res(c1, c1, td)
        self.out = nn.Sequential(nn.GroupNorm(8, c1), nn.SiLU(), nn.Conv2d(c1, 3, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    def forward(
        self, z: torch.Tensor, masked: torch.Tensor, hole: torch.Tensor, t: torch.Tensor
    ) -> torch.Tensor:
        e = self.temb(_timestep_embedding(t, self.tdim))
        h1 = self.d1b(self.d1a(self.inp(torch.cat([z, masked, hole], 1)), e), e)
        h2 = self.d2b(self.d2a(self.down1(h1), e), e)
        m = self.m1(self.down2(h2), e)
        m = self.m2(m + F.silu(self.mid_dil(m)), e)
        u2 = self.u2b(self.u2a(torch.cat([self.up2(m), h2], 1), e), e)
        u1 = self.u1b(self.u1a(torch.cat([self.up1(u2), h1], 1), e), e)
        return self.out(u1)


@dataclass
class PriorCondition:
    """masked (B, 3, H, W) in [-1, 1] with 0 in the hole; hole (B, 1, H, W) in {0, 1}."""

    masked: torch.Tensor
    hole: torch.Tensor


class ScenePrior(Denoiser):
    """The trained scene prior as a :class:`Denoiser` (pixel space: latent = 2 image - 1)."""

    name = NAME

    def __init__(self, net: InpaintUNet, cfg: ScenePriorConfig, info: dict | None = None) -> None:
        self.net = net.eval().requires_grad_(False)
        self.cfg = cfg
        self.prediction_type = cfg.prediction_type
        self.work_size = cfg.patch
        self.info = info or {}

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Image (B, 3, H, W) in [0, 1] -> latent (B, 3, H, W) in [-1, 1]."""
        return 2 * x - 1

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent (B, 3, H, W) -> image in about [0, 1] (differentiable)."""
        return (z + 1) / 2

    def make_condition(self, image: torch.Tensor, mask: torch.Tensor, prompt: str = "") -> PriorCondition:
        """Condition for image (B, 3, H, W) in [0, 1], mask (B, 1, H, W) (1 = fill)."""
        if prompt:
            log.warning("%s has no text conditioning: prompt %r ignored", NAME, prompt)
        hole = (mask > 0.5).to(image.dtype)
        return PriorCondition((2 * image - 1) * (1 - hole), hole)

    def predict(self, z: torch.Tensor, t: torch.Tensor, cond: Any = None) -> torch.Tensor:
        if not isinstance(cond, PriorCondition):
            raise TypeError("ScenePrior.predict needs a PriorCondition (see make_condition)")
        return self.net(z.float(), cond.masked.float(), cond.hole.float(), t).to(z.dtype)

    def inpaint(
        self,
        image: torch.Tensor,
        mask: torch.Tensor,
        prompt: str = "",
        cfg: SamplerConfig | None = None,
        energy: EnergyFn | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Sample a fill of image (B, 3, H, W) [0, 1] under mask (B, 1, H, W); returns (B, 3, H, W) in
        [0, 1] (whole crop; H, W multiples of 4, ideally the working size P): the final x0 prediction."""
        cfg = cfg or SamplerConfig(num_steps=50, discretization="uniform", eta=0.0)
        cond = self.make_condition(image, mask, prompt)
        z = torch.randn(image.shape, generator=generator)
        res = DDIMSampler(self, cfg).sample(z, cond, None, energy=energy, generator=generator)
        # the last step's clean x0 prediction, not z at alpha_bar_0: in pixel space the latter keeps
        # sqrt(1 - alpha_bar_0) of predicted noise, which an undertrained prior makes visible (measured
        # on the SPIn-NeRF holes after 1 minute: HF ratio 2.0 -> 1.75, GMSD 0.221 -> 0.218)
        return self.decode(res.x0).clamp(0, 1)


# ----------------------------------------------------------------------------------------------------
# training data


def random_holes(rng: np.random.Generator, p: int) -> np.ndarray:
    """A synthetic hole mask (p, p) bool: 1-3 rectangles / ellipses / thick strokes, 5-50 % of the area."""
    for _ in range(20):
        m = np.zeros((p, p), np.uint8)
        for _ in range(int(rng.integers(1, 4))):
            kind = rng.integers(3)
            cy, cx = (int(v) for v in rng.integers(0, p, 2))
            if kind == 0:
                h, w = (int(v) for v in rng.integers(p // 8, p // 2 + 1, 2))
                m[max(cy - h // 2, 0) : cy + h // 2, max(cx - w // 2, 0) : cx + w // 2] = 1
            elif kind == 1:
                ax = tuple(int(v) for v in rng.integers(p // 10, p // 4 + 1, 2))
                cv2.ellipse(m, (cx, cy), ax, float(rng.uniform(0, 180)), 0, 360, 1, -1)
            else:
                pts = rng.integers(0, p, (int(rng.integers(2, 5)), 2)).astype(np.int32)
                cv2.polylines(m, [pts], False, 1, int(rng.integers(max(p // 16, 2), p // 6 + 2)))
        if 0.05 <= m.mean() <= 0.5:
            return m.astype(bool)
    return m.astype(bool)


class _PatchSampler:
    def __init__(self, images: list[np.ndarray], exclude: list[np.ndarray], cfg: ScenePriorConfig) -> None:
        self.img = [torch.from_numpy(np.ascontiguousarray(i.transpose(2, 0, 1))).float() for i in images]
        self.exc = [torch.from_numpy(e.astype(np.float32))[None] for e in exclude]
        self.cfg = cfg
        self.rng = np.random.default_rng(cfg.seed)
        p = cfg.patch
        self.scales = [s for s in cfg.scales if all(p * s <= min(i.shape[:2]) for i in images)]
        if not self.scales:
            raise ValueError(f"{NAME}: images are smaller than the patch size {p}")

    def batch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(x0 (B,3,P,P) in [-1,1], hole (B,1,P,P) conditioning hole, weight (B,1,P,P) loss weight)."""
        p, rng = self.cfg.patch, self.rng
        xs, holes, ws = [], [], []
        for _ in range(self.cfg.batch):
            k = int(rng.integers(len(self.img)))
            s = int(rng.choice(self.scales))
            img, exc = self.img[k], self.exc[k]
            H, W = img.shape[1:]
            for _ in range(10):  # prefer patches without excluded pixels
                y, x = int(rng.integers(0, H - p * s + 1)), int(rng.integers(0, W - p * s + 1))
                e = exc[:, y : y + p * s, x : x + p * s]
                if e.max() == 0:
                    break
            crop = img[:, y : y + p * s, x : x + p * s]
            if s > 1:
                crop, e = F.avg_pool2d(crop[None], s)[0], F.max_pool2d(e[None], s)[0]
            hole = torch.from_numpy(random_holes(rng, p))[None].float() * (1 - e)  # never inside exclusions
            w = (1 + (self.cfg.hole_weight - 1) * hole) * (1 - e)  # no loss where the truth is unknown
            xs.append(crop * 2 - 1)
            holes.append(torch.clamp(hole + e, 0, 1))
            ws.append(w)
        return torch.stack(xs), torch.stack(holes), torch.stack(ws)


# ----------------------------------------------------------------------------------------------------
# training and cache


def cache_key(images: list[np.ndarray], exclude: list[np.ndarray], cfg: ScenePriorConfig) -> str:
    """sha256 (hex, 24 chars) of the images, the excluded masks and the settings."""
    h = hashlib.sha256(f"scene-prior-v{_VERSION}".encode())
    h.update(repr(sorted(asdict(cfg).items())).encode())
    for im, ex in zip(images, exclude):
        h.update(np.ascontiguousarray(im, dtype=np.float32).tobytes())
        h.update(np.packbits(np.asarray(ex, bool)).tobytes())
    return h.hexdigest()[:24]


def _check_inputs(images: list[np.ndarray], exclude: list[np.ndarray] | None) -> list[np.ndarray]:
    if not images:
        raise ValueError(f"{NAME}: no training images given")
    if exclude is None:
        exclude = [np.zeros(i.shape[:2], bool) for i in images]
    if len(exclude) != len(images):
        raise ValueError(f"{NAME}: {len(images)} images but {len(exclude)} exclusion masks")
    for n, (im, ex) in enumerate(zip(images, exclude)):
        if im.ndim != 3 or im.shape[2] != 3:
            raise ValueError(f"{NAME}: image {n} must be (H, W, 3) float in [0, 1], got {im.shape}")
        if ex.shape != im.shape[:2]:
            raise ValueError(f"{NAME}: exclusion mask {n} is {ex.shape}, image is {im.shape[:2]}")
        if not np.isfinite(im).all():
            raise ValueError(f"{NAME}: image {n} contains NaN or Inf")
    return [np.asarray(e, bool) for e in exclude]


def denoising_loss(
    net: InpaintUNet,
    x0: torch.Tensor,
    hole: torch.Tensor,
    w: torch.Tensor,
    t: torch.Tensor,
    noise: torch.Tensor,
    acp: torch.Tensor,
    prediction_type: str,
) -> torch.Tensor:
    """Weighted MSE of the v (or eps) prediction; all tensors (B, C, P, P), t (B,) int64."""
    a = acp[t].float()[:, None, None, None]
    z = a.sqrt() * x0 + (1 - a).sqrt() * noise
    target = noise if prediction_type == "eps" else a.sqrt() * noise - (1 - a).sqrt() * x0
    out = net(z, x0 * (1 - hole), hole, t)
    return ((out - target) ** 2 * w).sum() / (w.sum() * 3).clamp_min(1.0)


def train_scene_prior(
    images: list[np.ndarray],
    exclude: list[np.ndarray] | None = None,
    cfg: ScenePriorConfig | None = None,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    ckpt_seconds: float = CKPT_SECONDS,
) -> ScenePrior:
    """Train (or load from the cache) the scene prior.

    images: list of (H, W, 3) float32 arrays in [0, 1]; exclude: list of (H, W) bool masks of pixels
    whose truth is unknown (the object masks, plus any held-out holes); they are never used as hole
    targets nor as loss. cache_dir: where ``scene_prior_<hash>.pt`` is kept (None = no cache);
    training also checkpoints there every `ckpt_seconds` (``scene_prior_<hash>.ckpt.pt``, removed
    when done) and a call that finds a checkpoint resumes from it: with `train_steps` set the
    resumed model is the one an uninterrupted run makes.
    """
    from tqdm import tqdm

    cfg = cfg or ScenePriorConfig()
    exclude = _check_inputs(images, exclude)
    path = None
    if cache_dir is not None:
        key = cache_key(images, exclude, cfg)
        path = Path(cache_dir) / f"scene_prior_{key}.pt"
        if path.is_file():
            blob = load_checkpoint(path, CACHE_REMEDY)
            net = InpaintUNet(cfg.base)
            try:
                net.load_state_dict(blob["state_dict"])
                train_s, n_steps = float(blob["info"]["train_s"]), int(blob["info"]["steps"])
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise malformed(path, exc, CACHE_REMEDY) from None
            log.info("%s: reusing cached model %s (trained %.0f s, %d steps)", NAME, path, train_s, n_steps)
            return ScenePrior(net, cfg, blob["info"] | {"cached": True, "path": str(path)})
    torch.manual_seed(cfg.seed)
    net = InpaintUNet(cfg.base)
    n_par = sum(p.numel() for p in net.parameters())
    sampler = _PatchSampler(images, exclude, cfg)
    acp = alphas_cumprod(cfg.schedule)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=0.0)
    g = torch.Generator().manual_seed(cfg.seed)
    total = cfg.train_steps
    if cfg.max_steps is not None:
        total = cfg.max_steps if total is None else min(total, cfg.max_steps)
    by_steps = cfg.train_steps is not None
    ckpt = None if path is None else path.with_name(path.stem + ".ckpt.pt")
    steps, ema, spent = 0, None, 0.0
    if ckpt is not None and ckpt.is_file():
        st = load_checkpoint(ckpt, CACHE_REMEDY)
        try:
            net.load_state_dict(st["net"])
            opt.load_state_dict(st["opt"])
            g.set_state(st["gen"])
            sampler.rng.bit_generator.state = st["rng"]
            steps, ema, spent = st["steps"], st["ema"], st["train_s"]
        except (KeyError, TypeError, AttributeError) as exc:
            raise malformed(ckpt, exc, CACHE_REMEDY) from None
        log.info("%s: resuming the interrupted training at step %d (%s)", NAME, steps, ckpt)
    log.info(
        "%s: training %.2f M parameters on %d images for %s (patch %d, scales %s)",
        NAME,
        n_par / 1e6,
        len(images),
        f"{total} steps" if by_steps else f"{cfg.train_seconds:.0f} s",
        cfg.patch,
        sampler.scales,
    )
    t0 = time.perf_counter() - spent
    last_ckpt = time.monotonic()
    bar = tqdm(total=total if by_steps else round(cfg.train_seconds), initial=steps if by_steps else 0,
               desc=NAME, unit="step" if by_steps else "s", disable=not progress, leave=False)  # fmt: skip
    net.train()
    while True:
        el = time.perf_counter() - t0
        if (total is not None and steps >= total) or (not by_steps and el >= cfg.train_seconds):
            break
        x0, hole, w = sampler.batch()
        t = torch.randint(1, cfg.schedule.num_train_steps, (x0.shape[0],), generator=g)
        noise = torch.randn(x0.shape, generator=g)
        loss = denoising_loss(net, x0, hole, w, t, noise, acp, cfg.prediction_type)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        steps += 1
        lv = loss.item()
        ema = lv if ema is None else 0.98 * ema + 0.02 * lv
        bar.n = steps if by_steps else min(round(time.perf_counter() - t0), bar.total)
        bar.set_postfix(loss=f"{ema:.4f}", steps=steps, refresh=False)
        bar.refresh()
        if ckpt is not None and time.monotonic() - last_ckpt >= ckpt_seconds:
            state = {"net": net.state_dict(), "opt": opt.state_dict(), "gen": g.get_state(),
                     "rng": sampler.rng.bit_generator.state, "steps": steps, "ema": ema,
                     "train_s": time.perf_counter() - t0}  # fmt: skip
            atomic_write(ckpt, lambda p, st=state: torch.save(st, p))
            last_ckpt = time.monotonic()
    bar.close()
    net.eval()
    info = {
        "train_s": time.perf_counter() - t0,
        "steps": steps,
        "steps_asked": total,
        "loss_ema": ema,
        "params": n_par,
        "cached": False,
    }
    log.info("%s: trained %d steps in %.1f s, loss %.4f", NAME, steps, info["train_s"], ema or float("nan"))
    if path is not None:
        blob = {"state_dict": net.state_dict(), "config": asdict(cfg), "info": info}
        atomic_write(path, lambda p: torch.save(blob, p))  # a reader never sees a half-written model
        ckpt.unlink(missing_ok=True)
        info["path"] = str(path)
    return ScenePrior(net, cfg, info)


@torch.no_grad()
def heldout_x0_error(
    prior: ScenePrior, x0: torch.Tensor, hole: torch.Tensor, ts: list[int], generator: torch.Generator
) -> dict[str, float]:
    """Mean squared x0 error inside the hole on held-out patches, averaged over timesteps ts.

    x0: (B, 3, P, P) in [-1, 1], hole (B, 1, P, P). Returns the model's error and two baselines:
    'identity' (x0 estimate = z_t itself) and 'mean' (x0 estimate = the mean known colour of the patch).
    """
    acp = alphas_cumprod(prior.cfg.schedule)
    cond = PriorCondition(x0 * (1 - hole), hole)
    known = 1 - hole
    mean_col = (x0 * known).sum((2, 3), keepdim=True) / known.sum((2, 3), keepdim=True).clamp_min(1)
    errs = {"model": 0.0, "identity": 0.0, "mean": 0.0}
    nh = hole.sum() * 3
    for t in ts:
        a = float(acp[t])
        z = math.sqrt(a) * x0 + math.sqrt(1 - a) * torch.randn(x0.shape, generator=generator)
        xh, _ = split_prediction(
            prior.predict(z, torch.full((x0.shape[0],), t), cond), z, a, prior.prediction_type
        )
        for k, est in (("model", xh), ("identity", z), ("mean", mean_col.expand_as(x0))):
            errs[k] += float((((est - x0) ** 2) * hole).sum() / nh) / len(ts)
    return errs
