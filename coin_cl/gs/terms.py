"""Loss terms: what the trainer minimises, as a list of pluggable objects.

Per step the trainer renders one view, builds a `LossContext` and minimises

    total = sum(term.weight * term(ctx) for term in terms)

The protocol (duck-typed; `LossTerm` gives the defaults):

- `name: str` — unique among a trainer's terms; keys the term's logged value and its checkpoint
  state;
- `weight: float` — multiplies the term's value (its lambda);
- `auxiliary: bool` — a prior on the geometry whose gradient the trainer caps against the
  photometric part's (`coin_cl.gs.balance`); default False;
- `__call__(ctx) -> Tensor` — a scalar, differentiable with respect to the model's parameters
  through `ctx.out`; it may add logged scalars to `ctx.log`;
- `before_render(view, index, step, model) -> dict` — optional; extra keyword arguments for
  `model.render` of this step (a depth loss asks `return_depth=True` on its view; Ref-GS's anchor
  attention passes `features=`, the attended anchor features). Two terms may not set the same key;
- `step_after(ctx)` — called after the model's optimiser step of every training step, before
  densification changes the primitives. A term with parameters of its own (an adversarial
  discriminator) updates them here with its own optimiser; the generator's backward may have
  left gradients on them, so it clears them first;
- `state_dict()` / `load_state_dict(sd)` — anything the term must carry across a checkpoint
  (per-view statistics, its own networks and optimiser), so that resumed runs stay bit-exact.

Per-view weights (CoIn's W_n) come from a `ViewWeights` source given to `PhotometricLoss`:
`StaticViewWeights` reads `View.weight`; Ref-GS's adaptive weights replace it and see the view's
current unweighted photometric loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.losses import LossConfig, photometric_map

if TYPE_CHECKING:
    from coin_cl.gs.base import Model, RenderOutput
    from coin_cl.gs.data import View


@dataclass
class LossContext:
    """Everything a loss term may look at for one training step.

    view: the training view (camera, target image [H, W, 3], exclusion mask [H, W] or None,
        static weight); index: its position in the trainer's training views (for per-view state);
    out: the model's render of it (image [H, W, 3], alpha, depth, meta); step: counted from 0;
    model: the model being trained; log: scalars terms want in the training log (floats).
    """

    view: View
    index: int
    out: RenderOutput
    step: int
    model: Model
    log: dict[str, float] = field(default_factory=dict)


class LossTerm:
    """Base loss term: override `__call__`; the other hooks default to doing nothing."""

    name: str = "term"
    weight: float = 1.0
    # A prior on the geometry (a depth term) rather than the images: the trainer holds its gradient
    # below the photometric part's (`TrainConfig.aux_grad_ratio`, `coin_cl.gs.balance`).
    auxiliary: bool = False

    def __call__(self, ctx: LossContext) -> Tensor:
        raise NotImplementedError

    def before_render(self, view: View, index: int, step: int, model: Model) -> dict[str, Any]:
        """Extra keyword arguments for this step's `model.render` (default none)."""
        return {}

    def step_after(self, ctx: LossContext) -> None:
        """After the model's optimiser step (a term's own optimiser steps here)."""

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        pass


class ViewWeights:
    """Per-view weight source for `PhotometricLoss`; this base returns each view's static
    `View.weight` (0 removes the view).

    `__call__(ctx, view_loss)` gets the view's current unweighted photometric loss (a detached
    scalar) so adaptive schemes (Ref-GS: W_n from the change of L_R^n between visits) can use it;
    it returns a float or a scalar Tensor. State for checkpoints as for loss terms.
    """

    def __call__(self, ctx: LossContext, view_loss: Tensor) -> float | Tensor:
        return float(ctx.view.weight)

    def step_after(self, ctx: LossContext) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        pass


StaticViewWeights = ViewWeights


@dataclass
class PhotometricLoss(LossTerm):
    """W_n x ((1 - lambda) L1 + lambda (1 - SSIM)) over the view's kept pixels (paper eq. 2;
    `coin_cl.gs.losses.photometric_loss`), W_n from `view_weights`; with `weighted_regions`, W_n
    weighs only the pixels of the view's region and every other pixel counts once.

    Logs 'l1' and 'ssim' (over kept pixels) and 'view_weight'.
    """

    cfg: LossConfig = field(default_factory=LossConfig)
    view_weights: ViewWeights = field(default_factory=StaticViewWeights)
    weight: float = 1.0
    name: str = "photometric"
    # Per trainer view, the [H, W] bool pixels W_n weighs (Ref-GS: the inpainting masks, where the
    # views' targets disagree and the reference arbitrates); the rest of the view counts with
    # weight 1. None (default): W_n weighs the whole view.
    weighted_regions: Sequence[np.ndarray] | None = None

    def __call__(self, ctx: LossContext) -> Tensor:
        v = ctx.view
        # The fused path runs SSIM as one OpenCL op (kernels/ssim.cl) instead of torch convolutions;
        # a term evaluated without a model (model=None) takes the torch path.
        fused = getattr(ctx.model, "fused", False)
        px, parts = photometric_map(
            ctx.out.image[None], v.image[None], None if v.exclude is None else v.exclude[None], self.cfg,
            backend="opencl" if fused else "torch", device=getattr(ctx.model, "device", None),
        )  # fmt: skip
        w = self.view_weights(ctx, parts["loss"][0])
        w = torch.as_tensor(w, dtype=px.dtype)
        ctx.log.update(l1=float(parts["l1"][0]), ssim=float(parts["ssim"][0]), view_weight=float(w))
        if self.weighted_regions is not None and float(v.weight) != 0:
            region = torch.as_tensor(np.asarray(self.weighted_regions[ctx.index], bool))
            # where(): a zero W_n drops the region's pixels with an exactly zero gradient
            inside = torch.where(region, px[0], torch.zeros_like(px[0])).sum()
            outside = torch.where(region, torch.zeros_like(px[0]), px[0]).sum()
            return outside + torch.where(w != 0, w * inside, torch.zeros_like(inside))
        loss = px[0].sum()
        # A zero weight must give an exactly zero gradient even if the view's loss is not finite
        # (and keep a graph, so that backward still runs when this is the only term).
        return torch.where(w != 0, w * loss, torch.zeros_like(loss))

    def step_after(self, ctx: LossContext) -> None:
        self.view_weights.step_after(ctx)

    def state_dict(self) -> dict[str, Any]:
        return {"view_weights": self.view_weights.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.view_weights.load_state_dict(sd.get("view_weights", {}))


@dataclass
class ScaleVolumeReg(LossTerm):
    """Mean volume prod(scales) of the drawn Gaussians (`out.meta['scales']` [M, 3]); Scaffold-GS
    adds it with weight 0.01 to keep neural Gaussians from bloating. A view whose static weight is
    0 is switched off entirely, so it adds nothing there either."""

    weight: float = 0.01
    name: str = "scale_reg"

    def __call__(self, ctx: LossContext) -> Tensor:
        scales = ctx.out.meta["scales"]
        if ctx.view.weight == 0 or scales.shape[0] == 0:
            return ctx.out.image.new_zeros(())
        return scales.prod(dim=1).mean()


@dataclass
class NeedleReg(LossTerm):
    """Mean over the drawn Gaussians (`out.meta['scales']` [M, 3]) of
    max(0, log(s_max / s_mid) - log(max_ratio)), s_max >= s_mid >= s_min their sorted scales.

    A needle (one axis many times both others) draws a streak across every view it crosses; a disk
    (two large axes, one small: a surface) is left alone, since only the two largest axes are
    compared. Zero, with a zero gradient, for every Gaussian whose longest axis is at most
    `max_ratio` times its middle one; in log space, so a needle's pull does not grow with its
    length. With `in_mask`, the mean is over the Gaussians whose centre falls inside the view's
    `meta['mask']` ([H, W] bool: the region no photo constrains), so that the weight means the same
    whatever share of the view the mask is; elsewhere the photos constrain the shape (a model whose
    scales come from one shared network, Scaffold-GS's, is pulled everywhere a little). A view whose
    static weight is 0, or without a mask (or with no Gaussian centred in it) when `in_mask` is
    set, adds nothing.
    """

    weight: float = 0.1
    max_ratio: float = 4.0
    in_mask: bool = False
    name: str = "needle_reg"

    def __post_init__(self) -> None:
        if not (self.max_ratio >= 1.0 and np.isfinite(self.max_ratio)):
            raise ValueError(f"NeedleReg.max_ratio is {self.max_ratio!r}: give a finite ratio >= 1")
        if not (self.weight >= 0 and np.isfinite(self.weight)):
            raise ValueError(f"NeedleReg.weight is {self.weight!r}: give a finite weight >= 0")

    def __call__(self, ctx: LossContext) -> Tensor:
        scales = ctx.out.meta["scales"]
        mask = ctx.view.meta.get("mask") if self.in_mask else None
        if ctx.view.weight == 0 or scales.shape[0] == 0 or (self.in_mask and mask is None):
            return ctx.out.image.new_zeros(())
        top2 = scales.topk(2, dim=1).values.clamp_min(torch.finfo(scales.dtype).tiny)
        excess = (top2[:, 0].log() - top2[:, 1].log() - float(np.log(self.max_ratio))).clamp_min(0.0)
        if mask is not None:
            mask = torch.as_tensor(np.asarray(mask, bool))
            h, w = mask.shape
            m2 = ctx.out.meta["means2d"].detach()
            # Drawn ones only: a culled splat's (behind the camera, NaN input) centre means nothing.
            drawn = ctx.out.meta.get("visible", torch.ones(m2.shape[0], dtype=torch.bool))
            px = torch.nan_to_num(m2, nan=-1.0).clamp(-1, max(w, h)).floor().long()
            on = drawn & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
            inside = torch.zeros_like(on)
            inside[on] = mask[px[on, 1], px[on, 0]]
            if not bool(inside.any()):
                return ctx.out.image.new_zeros(())
            excess = excess[inside]
        return excess.mean()


def default_terms(kind: str, loss_cfg: LossConfig | None = None) -> list[LossTerm]:
    """The published loss of a model kind: photometric (both), + 0.01 x scale volume (Scaffold-GS)."""
    terms: list[LossTerm] = [PhotometricLoss(loss_cfg or LossConfig())]
    if kind == "scaffold":
        terms.append(ScaleVolumeReg())
    elif kind != "3dgs":
        raise ValueError(f"no default loss terms for model {kind!r}")
    return terms
