"""Ref-GS as trainer plug-ins (paper 4.2, issue 11): the building blocks of `coin_cl.gs.refgs`
wrapped in the `coin_cl.gs.terms` protocol, so the generic `Trainer` runs Ref-GS without knowing it.

* `AdaptiveWeightSource` — a `ViewWeights` for `PhotometricLoss`: W_n from `AdaptiveViewWeights`
  (lambda_r on the reference, the sigmoid of the loss change elsewhere) times the view's static
  weight. Its state (previous loss per view, history) rides in the photometric term's checkpoint.
* `ReferenceDepthTerm` — lambda_D x mean |A R_k + B - D_k| on the reference view only; asks the
  render for depth (`before_render`) on that view, valid pixels = rendered alpha > `min_alpha`.
* `AnchorAttentionTerm` — contributes no loss; in `before_render` it attends the in-mask anchors'
  features to the ring's (`AnchorAttention.apply_view`) and hands the result to the render as
  `features=`; in `step_after` it steps its own Adam (lr `RefGSConfig.attn_lr(iters)`) and writes
  the attended rows back into the feature parameter (`attn_write_back`).
* `refgs_terms` builds the list from a `RefGSConfig`; each switch removes exactly its piece.

View keys are the trainer's training-view indices (`LossContext.index`), so `ref_index` and the
`masks` list are in that order, not the scene's.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.base import Model
from coin_cl.gs.data import View
from coin_cl.gs.losses import LossConfig
from coin_cl.gs.refgs import (
    AdaptiveViewWeights,
    AnchorAttention,
    RefGSConfig,
    reference_depth_loss,
    write_back_features,
)
from coin_cl.gs.terms import LossContext, LossTerm, PhotometricLoss, ScaleVolumeReg, ViewWeights

log = logging.getLogger(__name__)

# Below this many valid (alpha > min_alpha) pixels the affine fit of the depth prior is noise;
# the reference step then goes without the depth term (counted in `n_skipped`).
MIN_DEPTH_PIXELS = 16


class AdaptiveWeightSource(ViewWeights):
    """Ref-GS's W_n as a `ViewWeights` source (see `AdaptiveViewWeights`).

    Gets the view's current unweighted photometric loss from `PhotometricLoss`; returns
    W_n x `View.weight` (so a view switched off statically stays off). With
    `weights.enabled=False` (ablation) W_n is 1.0 for every view, the reference included.
    """

    def __init__(self, weights: AdaptiveViewWeights):
        self.weights = weights

    def __call__(self, ctx: LossContext, view_loss: Tensor) -> float:
        return self.weights.weight(ctx.index, view_loss, ctx.step) * float(ctx.view.weight)

    def state_dict(self) -> dict[str, Any]:
        return {"adaptive": self.weights.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if "adaptive" in sd:
            self.weights.load_state_dict(sd["adaptive"])


class ReferenceDepthTerm(LossTerm):
    """The reference depth loss L_D (weight = lambda_D): zero on every view but `ref_index`.

    Args:
        ref_index: the reference's trainer view index.
        prior: [H, W] depth prior D_k; mask: [H, W] bool, the reference's mask (left out of the
            affine fit); disparity: the prior is a disparity (fit in its space).
        min_alpha: pixels whose rendered alpha is at most this are neither fitted nor penalised
            (their expected depth depth / alpha is ill-defined).
    """

    name = "ref_depth"

    def __init__(
        self,
        ref_index: int,
        prior: np.ndarray | Tensor,
        mask: np.ndarray | Tensor,
        weight: float = 10.0,
        disparity: bool = False,
        min_alpha: float = 0.5,
    ):
        self.ref_index = int(ref_index)
        self.prior = torch.as_tensor(np.asarray(prior, np.float32))
        self.mask = torch.as_tensor(np.asarray(mask, bool))
        if self.prior.shape != self.mask.shape or self.prior.dim() != 2:
            raise ValueError(
                f"prior {tuple(self.prior.shape)} and mask {tuple(self.mask.shape)} must be [H, W]"
            )
        self.weight = float(weight)
        self.disparity = bool(disparity)
        self.min_alpha = float(min_alpha)
        self.n_applied = 0
        self.n_skipped = 0
        self.last_fit: dict[str, float] = {}

    def before_render(self, view: View, index: int, step: int, model: Model) -> dict[str, Any]:
        return {"return_depth": True} if index == self.ref_index else {}

    def __call__(self, ctx: LossContext) -> Tensor:
        zero = ctx.out.image.new_zeros(())
        if ctx.index != self.ref_index:
            return zero
        if ctx.out.depth is None:
            raise RuntimeError(
                "reference depth term: the render returned no depth (before_render not honoured)"
            )
        valid = ctx.out.alpha.detach() > self.min_alpha
        if int(valid.sum()) < MIN_DEPTH_PIXELS:
            self.n_skipped += 1
            log.debug("reference depth loss skipped at step %d: %d valid pixels", ctx.step, int(valid.sum()))
            return zero
        loss, fit = reference_depth_loss(ctx.out.depth, self.prior, self.mask, 1.0, valid, self.disparity)
        self.n_applied += 1
        self.last_fit = {"step": ctx.step, **fit}
        return loss

    def state_dict(self) -> dict[str, Any]:
        return {"n_applied": self.n_applied, "n_skipped": self.n_skipped, "last_fit": dict(self.last_fit)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.n_applied = int(sd.get("n_applied", 0))
        self.n_skipped = int(sd.get("n_skipped", 0))
        self.last_fit = dict(sd.get("last_fit", {}))


class AnchorAttentionTerm(LossTerm):
    """Anchor feature attention in every training view (no loss of its own: value 0).

    Per step (once `cfg.attention_active(step, iters)`): the in-mask anchors of the view
    (`masks[index]`) attend to the ring's; the render uses the attended features, so the
    photometric gradient reaches the attention's query/key projections, which this term's Adam
    steps in `step_after` (lr `cfg.attn_lr(iters)`), and then the attended rows are written into
    the feature parameter when `cfg.attn_write_back`. Empty sets: no override that step
    (`n_skipped`). Needs a model whose render takes `features=` (Scaffold-GS).
    """

    name = "attention"

    def __init__(self, attn: AnchorAttention, masks: Sequence[np.ndarray], cfg: RefGSConfig, iters: int):
        self.attn = attn
        self.masks = [np.asarray(m, bool) for m in masks]
        self.cfg = cfg
        self.iters = int(iters)
        self.lr = cfg.attn_lr(self.iters)
        self.weight = 1.0
        self.opt = torch.optim.Adam(self.attn.parameters(), lr=self.lr(0), eps=1e-15)
        self.n_applied = 0
        self.n_skipped = 0
        self._pending: tuple[Tensor, Tensor] | None = None

    def before_render(self, view: View, index: int, step: int, model: Model) -> dict[str, Any]:
        self._pending = None
        if not self.cfg.attention_active(step, self.iters):
            return {}
        if "features" not in model.optimizer.params:
            raise ValueError(
                f"anchor attention needs a model with anchor features (Scaffold-GS), not {model.kind!r}"
            )
        # Gradients of the last applied step were consumed by its Adam step; start clean.
        self.opt.zero_grad(set_to_none=True)
        p = model.optimizer.params
        feats, info = self.attn.apply_view(
            p["features"], p["anchors"].detach(), view.camera, self.masks[index],
            self.cfg.ring_frac, self.cfg.ring_min_px,
        )  # fmt: skip
        if info["skipped"] is not None:
            self.n_skipped += 1
            return {}
        self.n_applied += 1
        self._pending = (feats, info["updated"])
        return {"features": feats}

    def __call__(self, ctx: LossContext) -> Tensor:
        ctx.log["attn_applied"] = float(self._pending is not None)
        return ctx.out.image.new_zeros(())

    def step_after(self, ctx: LossContext) -> None:
        if self._pending is None:
            return
        feats, updated = self._pending
        self._pending = None
        grads = [q.grad for q in self.attn.parameters() if q.grad is not None]
        if any(not bool(torch.isfinite(g).all()) for g in grads):
            # The model's own guard has already passed, so this is the attention alone: skip its
            # update rather than poison the projections.
            log.warning("anchor attention: non-finite gradient at step %d; its update is skipped", ctx.step)
        else:
            for group in self.opt.param_groups:
                group["lr"] = self.lr(ctx.step)
            self.opt.step()
        if self.cfg.attn_write_back:
            write_back_features(ctx.model.optimizer.params["features"], feats, updated)

    def state_dict(self) -> dict[str, Any]:
        return {"attn": self.attn.state_dict(), "opt": self.opt.state_dict(),
                "n_applied": self.n_applied, "n_skipped": self.n_skipped}  # fmt: skip

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.attn.load_state_dict(sd["attn"])
        self.opt.load_state_dict(sd["opt"])
        self.n_applied = int(sd["n_applied"])
        self.n_skipped = int(sd["n_skipped"])


def refgs_terms(
    cfg: RefGSConfig,
    ref_index: int,
    masks: Sequence[np.ndarray],
    iters: int,
    *,
    feat_dim: int = 32,
    depth_prior: np.ndarray | None = None,
    depth_is_disparity: bool = False,
    loss_cfg: LossConfig | None = None,
) -> list[LossTerm]:
    """Scaffold-GS's published loss plus Ref-GS's pieces, as `RefGSConfig` switches them.

    Always: `PhotometricLoss` (with `AdaptiveWeightSource`; constant 1 when
    `cfg.adaptive_weights` is off) and `ScaleVolumeReg`. `ReferenceDepthTerm` when
    `cfg.depth_loss` (needs `depth_prior` [H, W]); `AnchorAttentionTerm` when `cfg.feature_attention`.

    Args:
        ref_index: the reference's trainer view index; masks: [H, W] bool per trainer view.
        iters: the run's length (attention start and lr schedule).
    """
    weights = AdaptiveViewWeights.from_config(cfg, ref_index)
    terms: list[LossTerm] = [
        PhotometricLoss(loss_cfg or LossConfig(), view_weights=AdaptiveWeightSource(weights)),
        ScaleVolumeReg(),
    ]
    if cfg.depth_loss:
        if depth_prior is None:
            raise ValueError("cfg.depth_loss is on but no depth prior was given")
        terms.append(
            ReferenceDepthTerm(ref_index, depth_prior, masks[ref_index], cfg.lambda_depth, depth_is_disparity)
        )
    if cfg.feature_attention:
        terms.append(AnchorAttentionTerm(AnchorAttention.from_config(cfg, feat_dim), masks, cfg, iters))
    return terms


def adaptive_weights_of(terms: Sequence[LossTerm]) -> AdaptiveViewWeights | None:
    """The `AdaptiveViewWeights` inside a term list built by `refgs_terms` (None if absent)."""
    for t in terms:
        vw = getattr(t, "view_weights", None)
        if isinstance(vw, AdaptiveWeightSource):
            return vw.weights
    return None
