"""TE-D, the texture-enhancing discriminator (paper 4.4, 5.1): the fine stage.

Starting from the Ref-GS scene it trains in two phases, each a resumable `Trainer` run in its own
folder:

1. fine-tune: the photometric loss against the CLG images I~_n (I^_n where CLG skipped a view);
2. adversarial: L = L_R(R_n, I~_n) + lambda_gen L_gen(R_n, I^_n) (+ any extra terms the caller
   passes, e.g. Ref-GS's reference depth term, the paper's lambda_D L_D), where L_gen is the
   non-saturating generator loss of a PatchGAN (`coin_cl.diffusion.discriminator`) on 64x64
   patches drawn near the view's mask: "real" = patches of the initial inpaint I^_n, "fake" = the
   same windows of the render R_n. The discriminator takes one Adam step (pix2pix's lr 2e-4,
   betas (0.5, 0.999)) after every GS step, on the fake patches of that step, detached: a 1:1
   ratio, as pix2pix.

The primitives are fixed in this stage (no densification): it refines the appearance of the coarse
structure Ref-GS built (its learning rates: `TEDConfig.rates`). The paper runs 10k + 10k
iterations; a CoIn run takes its counts from the budget plan (`pipeline.budget`) unless
`TEDConfig.iters_*` give them; the plan gives the adversarial phase 0 steps where stage 1's fills
are not a learned inpainter's (`coin_plan.adversarial_skip`).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.diffusion.discriminator import (
    PatchDiscriminator,
    PatchGANConfig,
    crop_patches,
    d_loss,
    g_loss,
    sample_patch_corners,
)
from coin_cl.gs.model_kinds import continue_rates
from coin_cl.gs.strategy import Strategy
from coin_cl.gs.terms import LossContext, LossTerm, NeedleReg, PhotometricLoss
from coin_cl.gs.trainer import TrainConfig, Trainer
from coin_cl.timing import mean_step_seconds

if TYPE_CHECKING:
    from coin_cl.gs.base import Model

log = logging.getLogger(__name__)

RATES = ("restart", "continue")  # TEDConfig.rates, as a run resolves it ("auto" besides)


@dataclass
class TEDConfig:
    """TE-D's settings (paper 4.4); each field says what it means where it is declared. Fields left
    None are the run's: the budget plan's step counts (OUT/plan.json) and the run's seed."""

    # Steps of the fine-tuning phase (>= 0; 0 skips it; the paper: 10k). None (default): in a CoIn
    # run the budget plan decides (plan.json); `run_ted` on its own needs a number. A number is an
    # explicit count of the plan, like `CoInConfig.iters_ted_finetune`, which must then agree.
    iters_finetune: int | None = None
    # Steps of the adversarial phase (>= 0; as `iters_finetune`; the paper: 10k).
    iters_adversarial: int | None = None
    # Weight of the generator loss (>= 0). Default 0.01: the paper's.
    lambda_gen: float = 0.01
    # Patch side, px (a multiple of 8, >= 32). Default 64: the paper's; smaller images use their
    # shorter side rounded down to a multiple of 8 (`patch_size`).
    patch: int = 64
    # Patches per step (>= 1). Default 4.
    n_patches: int = 4
    # The patch sampler's band around the mask, px (>= 0). Default 32.
    margin: int = 32
    # Probability of drawing a patch centre from that band ([0, 1]). Default 1.0: every patch near
    # the mask, so the term only touches pixels near the inpainted region.
    p_near: float = 1.0
    # The discriminator's Adam learning rate (> 0). Default 2e-4: pix2pix's.
    lr_d: float = 2e-4
    # The discriminator's Adam betas (each in [0, 1)). Default (0.5, 0.999): pix2pix's.
    betas_d: tuple[float, float] = (0.5, 0.999)
    # Learning rates. "continue": Ref-GS lays its decay and growth out over its own and the
    # fine-tune's planned steps and the fine-tune goes on from where Ref-GS left them (`run_ted`'s
    # steps_before), the adversarial phase holding the final rates: one fit of both stages' steps.
    # "restart": each phase starts the model's schedules again from their initial rates (the
    # offsets' 100x its final one) and decays them over Ref-GS's steps, as a fresh trainer does.
    # "auto" (default): "continue" in a removal run, "restart" in an insertion run and in `run_ted`
    # on its own. At equal steps (docs/RUN.md) "continue" left less of the removed volume in front
    # of the background on cup_plain (ghost 0.056 / 0.079 against 0.072 / 0.127 in two runs), the
    # masked VGG distance and GMSD level, m-PSNR +0.65 / -0.22 dB; on SPIn-NeRF it was 0.13 dB
    # lower in m-PSNR and 1.4% higher in masked VGG distance, ghost level. On the synthetic
    # insertion room it let the inserted object's colour leak past its region (0.8% against none),
    # so insertion restarts.
    rates: str = "auto"
    # Needles in the hole: Gaussians whose centre falls inside a view's mask pay for a longest axis
    # more than this many times their middle one (`coin_cl.gs.terms.NeedleReg`, in both phases;
    # >= 1, or 0 for none). Default 4. Measured on SPIn-NeRF scene 1 at budget 30, TE-D alone on one
    # run's stages 0-3 at its 695 + 660 steps: without it half the Gaussians centred in the masks
    # had a longest axis over 5x their middle one (0.2% with it), drawn as streaks across the
    # bench; m-PSNR 12.53 -> 12.72, bbox GMSD 0.282 -> 0.279, masked VGG distance 4.042 -> 4.105.
    # At budget 10 on SPIn-NeRF and cup_plain every figure moved by under 0.5%.
    needle_ratio: float = 4.0
    # The needle term's weight (>= 0). Default 0.1, the setting measured above (not tuned).
    needle_weight: float = 0.1
    # Patch RNG seed. None (default): in a CoIn run the run's seed (`CoInConfig.seed`); `run_ted` on
    # its own: 0.
    seed: int | None = None

    def __post_init__(self) -> None:
        for name in ("iters_finetune", "iters_adversarial"):
            n = getattr(self, name)
            if n is not None and not (isinstance(n, int) and n >= 0):
                raise ValueError(f"TEDConfig.{name} is {n!r}: give a step count >= 0 (0 skips the phase), "
                                 "or None for the run's plan")  # fmt: skip
        for name, ok, what in (
            ("lambda_gen", self.lambda_gen >= 0, ">= 0"),
            ("patch", isinstance(self.patch, int) and self.patch >= 32 and self.patch % 8 == 0,
             "a multiple of 8, >= 32"),
            ("n_patches", isinstance(self.n_patches, int) and self.n_patches >= 1, ">= 1"),
            ("margin", isinstance(self.margin, int) and self.margin >= 0, ">= 0"),
            ("needle_ratio", self.needle_ratio == 0 or 1 <= self.needle_ratio < float("inf"), ">= 1, or 0"),
            ("needle_weight", 0 <= self.needle_weight < float("inf"), ">= 0"),
            ("p_near", 0.0 <= self.p_near <= 1.0, "in [0, 1]"),
            ("lr_d", self.lr_d > 0, "> 0"),
            ("betas_d", len(self.betas_d) == 2 and all(0.0 <= b < 1.0 for b in self.betas_d),
             "two numbers in [0, 1)"),
        ):  # fmt: skip
            if not ok:
                raise ValueError(f"TEDConfig.{name} is {getattr(self, name)!r}: give {what}")
        if self.rates not in ("auto", *RATES):
            raise ValueError(f"TEDConfig.rates is {self.rates!r}: use one of {('auto', *RATES)}")
        if self.seed is not None and not (isinstance(self.seed, int) and not isinstance(self.seed, bool)):
            raise ValueError(f"TEDConfig.seed is {self.seed!r}: give an integer, or None for the run's seed")


def patch_size(cfg: TEDConfig, height: int, width: int) -> int:
    """The patch side for an image: cfg.patch, or the largest multiple of 8 that fits (>= 32)."""
    p = min(cfg.patch, (min(height, width) // 8) * 8)
    if p < 32:
        raise ValueError(f"image {width}x{height} is too small for TE-D's patches (at least 32x32 needed)")
    return p


def probe_discriminator_seconds(
    cfg: TEDConfig,
    height: int,
    width: int,
    disc_cfg: PatchGANConfig | None = None,
    steps: int = 3,
    warmup: int = 1,
) -> float:
    """Seconds the discriminator adds to one adversarial step on this machine: the generator loss's
    forward and backward through it on `cfg.n_patches` patches of the image's patch size, then its
    own update on real and fake patches (`AdversarialTerm`), on random pixels (the cost does not
    depend on them); mean of `steps` after `warmup`. The plan adds it to a fine-tune step: a fixed
    ratio to a GS step, measured on 504x284 images (1.0), was 2.2 on the 192x144 room, where a GS
    step is cheap and the discriminator is not."""
    p = patch_size(cfg, height, width)
    g = torch.Generator().manual_seed(0)
    with torch.random.fork_rng():
        torch.manual_seed(0)
        disc = PatchDiscriminator(disc_cfg)
    disc.train()
    opt = torch.optim.Adam(disc.parameters(), lr=cfg.lr_d, betas=cfg.betas_d)
    real = torch.rand((cfg.n_patches, 3, p, p), generator=g)

    def step() -> None:
        fake = torch.rand((cfg.n_patches, 3, p, p), generator=g).requires_grad_(True)
        g_loss(disc(fake)).backward()
        opt.zero_grad(set_to_none=True)
        d_loss(disc(real), disc(fake.detach())).backward()
        opt.step()

    return mean_step_seconds(step, steps, warmup)


class AdversarialTerm(LossTerm):
    """lambda_gen * L_gen on patches of the render near the view's mask; trains its discriminator in
    `step_after`. Views whose `meta` has no 'real' image or an empty 'mask' contribute zero.

    View.meta needs 'real' [H, W, 3] (I^_n) and 'mask' [H, W] bool (the inpainting mask).
    """

    name = "adversarial"

    def __init__(self, cfg: TEDConfig, disc_cfg: PatchGANConfig | None = None):
        cfg = replace(cfg, seed=0 if cfg.seed is None else cfg.seed)
        self.cfg = cfg
        self.weight = cfg.lambda_gen
        with torch.random.fork_rng():  # seeded init without touching the caller's global RNG
            torch.manual_seed(cfg.seed)
            self.disc = PatchDiscriminator(disc_cfg)
        self.disc.train()  # BatchNorm in training mode (eval-mode statistics broke it, see its tests)
        self.opt = torch.optim.Adam(self.disc.parameters(), lr=cfg.lr_d, betas=cfg.betas_d)
        self.rng = np.random.default_rng(cfg.seed)
        self._pending: tuple[Tensor, Tensor] | None = None
        self.last: dict[str, Any] = {}

    def __call__(self, ctx: LossContext) -> Tensor:
        zero = ctx.out.image.sum() * 0.0  # keeps a graph when the term is the only one
        real_img, mask = ctx.view.meta.get("real"), ctx.view.meta.get("mask")
        self._pending = None
        if real_img is None or mask is None or not bool(np.asarray(mask).any()):
            return zero
        H, W = ctx.out.image.shape[:2]
        p = patch_size(self.cfg, H, W)
        corners = sample_patch_corners(
            np.asarray(mask, bool), self.cfg.n_patches, p, self.cfg.p_near, self.cfg.margin, self.rng
        )
        fake = crop_patches(ctx.out.image.permute(2, 0, 1), corners, p)
        real = crop_patches(torch.as_tensor(real_img).permute(2, 0, 1), corners, p)
        loss = g_loss(self.disc(fake))
        self._pending = (real.detach(), fake.detach())
        self.last = {"corners": corners, "patch": p}
        ctx.log["gen"] = float(loss.detach())
        return loss

    def step_after(self, ctx: LossContext) -> None:
        if self._pending is None:
            return
        real, fake = self._pending
        self._pending = None
        # The generator's backward went through the discriminator: clear what it left there.
        self.opt.zero_grad(set_to_none=True)
        loss = d_loss(self.disc(real), self.disc(fake))
        loss.backward()
        self.opt.step()
        ctx.log["disc"] = float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        return {
            "disc": self.disc.state_dict(),
            "opt": self.opt.state_dict(),
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if not sd:
            return
        self.disc.load_state_dict(sd["disc"])
        self.opt.load_state_dict(sd["opt"])
        self.rng.bit_generator.state = sd["rng"]


def _train_phase(model, views, test, cfg: TrainConfig, out: Path, terms: list[LossTerm]):
    """One resumable phase; returns (its result, the trained model: a checkpoint load replaces it)."""
    tr = Trainer(model, views, test, cfg, out, strategy=Strategy(), terms=terms)
    if tr.ckpt_path is not None and tr.ckpt_path.is_file():
        tr.load_checkpoint()
        log.info("TE-D: resumed %s at step %d", out.name, tr.step)
    return tr.train(), tr.model


def run_ted(
    model: Model,
    views: list,
    test_views: list,
    out_dir: Path,
    cfg: TEDConfig,
    train_cfg: TrainConfig | None = None,
    extra_terms: list[LossTerm] = (),
    max_seconds: dict[str, float] | None = None,
    steps_before: int = 0,
) -> tuple[dict[str, Any], Model]:
    """Run both TE-D phases from `model` (the Ref-GS scene).

    Args:
        model: a `coin_cl.gs` model (Scaffold-GS or 3DGS) holding the Ref-GS result.
        views: training `View`s whose image is I~_n and whose meta holds 'real' (I^_n [H, W, 3])
            and 'mask' ([H, W] bool).
        test_views: held-out views for the trainers' evaluation (may be empty).
        out_dir: the stage folder; phases write `finetune/` and `adversarial/` (checkpoints, logs).
        extra_terms: more loss terms for both phases (e.g. the reference depth term).
        max_seconds: {"finetune" | "adversarial": a cap on that phase's training seconds} (the
            pipeline's budget plan; 0 or absent: `train_cfg.max_seconds`).
        steps_before: the steps `model` trained before (Ref-GS's): with `cfg.rates` "continue" its
            schedules go on from that step of theirs ("auto" restarts them here: only a CoIn run
            lays Ref-GS's schedules out over both stages).
    Returns:
        (a JSON-able record: the config and both phases' results, the final model).
    """
    out_dir = Path(out_dir)
    base = train_cfg or TrainConfig()
    for name in ("iters_finetune", "iters_adversarial"):
        if getattr(cfg, name) is None:
            raise ValueError(f"TEDConfig.{name} is None: give run_ted a step count (a CoIn run takes it "
                             "from its budget plan)")  # fmt: skip
    cfg = replace(cfg, seed=0 if cfg.seed is None else cfg.seed)
    res: dict[str, Any] = {"config": asdict(cfg)}
    shape: list[LossTerm] = []
    if cfg.needle_ratio:
        shape.append(NeedleReg(weight=cfg.needle_weight, max_ratio=cfg.needle_ratio, in_mask=True))
    shared = [*shape, *extra_terms]
    for phase, iters, terms in (
        ("finetune", cfg.iters_finetune, [PhotometricLoss(), *shared]),
        ("adversarial", cfg.iters_adversarial, [PhotometricLoss(), AdversarialTerm(cfg), *shared]),
    ):
        if iters <= 0:
            res[phase] = {"skipped": "0 iterations"}
            log.info("TE-D: %s phase skipped (0 iterations)", phase)
            continue
        cap = (max_seconds or {}).get(phase, base.max_seconds)
        pcfg = replace(base, iters=iters, export_ply=phase == "adversarial", max_seconds=cap)
        if cfg.rates == "continue":
            continue_rates(model, steps_before, iters)
        res[phase], model = _train_phase(model, views, test_views, pcfg, out_dir / phase, terms)
        steps_before = res[phase]["step"]  # the next phase goes on from where this one stopped
    return res, model
