"""Ref-GS (CoIn paper 4.2): the reference-adaptive coarse stage's switches and the
trainer terms they build. One concept per module:

* `coin_cl.gs.targets`: the training targets (inpaint inside the mask, captured outside; 5.1).
* `coin_cl.gs.prune`: SfM points inside the masks removed before the anchors are built.
* `coin_cl.gs.view_weights`: the per-view loss weight W_n.
* `coin_cl.gs.anchor_attention`: in-mask anchors attend to a ring of anchors around the mask.
* `coin_cl.gs.depth_prior`: the reference's depth loss, its affine fit and its prior D_k.
* `coin_cl.gs.background_depth`: every view's mask held to the surrounding surfaces' depth
  (no ghost of a removed object).
* `coin_cl.pipeline.reference`: which view is the reference k.

Every piece can be switched off through `RefGSConfig` for the paper's ablations (Table 4: w/o
adaptive weight, w/o feature attention, w/o Ref-GS); `refgs_terms` builds the trainer's loss list
from it, each switch removing exactly its piece. View keys are the trainer's training-view indices
(`LossContext.index`), so `ref_index` and the `masks` list are in that order, not the scene's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from coin_cl.gs import balance
from coin_cl.gs.anchor_attention import AnchorAttention, AnchorAttentionTerm
from coin_cl.gs.background_depth import BackgroundDepthTerm
from coin_cl.gs.depth_prior import ReferenceDepthTerm
from coin_cl.gs.losses import LossConfig
from coin_cl.gs.optim import ExpSchedule
from coin_cl.gs.terms import LossTerm, PhotometricLoss, ScaleVolumeReg
from coin_cl.gs.view_weights import AdaptiveViewWeights, AdaptiveWeightSource


@dataclass
class RefGSConfig:
    """Ref-GS switches and hyper-parameters (paper 4.2 and supplement C).

    Ablations: `adaptive_weights=False` (all views weight 1), `feature_attention=False`,
    `depth_loss=False`; all three plus `prune_points=False` is plain training on the inpaints.
    """

    # -- reference view: name or index; None = the rule of `coin_cl.pipeline.reference.choose_reference`.
    #    In a CoIn run it is the run's reference (`CoInConfig.ref`, recorded in log.json's 2_refgs
    #    settings), and setting another one here is an error.
    ref: str | int | None = None
    # -- targets: inpaint inside the mask, captured image outside (paper 5.1)
    composite: bool = True
    # -- pruning of the SfM points before anchors are built
    prune_points: bool = True
    prune_min_fraction: float = 0.5  # inside the mask in >= this fraction of the views seeing it
    prune_min_views: int = 1  # points seen by fewer views are kept (no evidence)
    # -- adaptive view weights W_n
    adaptive_weights: bool = True
    lambda_r: float = 50.0  # supplement: 50 or 100 depending on the scene
    first_visit_weight: float = 0.5  # sigmoid(0): the formula's value for an unchanged loss
    # The pixels W_n weighs: "mask" (default): each view's inpainting mask, where the views' targets
    # disagree and the reference arbitrates; outside it every view counts once. "view": the whole
    # view, the paper's letter. Under Adam a whole view weighted lambda_r = 50 fills the second
    # moments of every shared parameter (the MLPs), so in a run of a few thousand steps the other
    # views train at a fraction of their rate (about a fifteenth, estimated from the moments'
    # averages); their captured pixels agree and need no arbiter.
    weight_region: str = "mask"
    # -- anchor feature attention
    feature_attention: bool = True
    attn_heads: int = 4  # value channels are split into heads: feat_dim % attn_heads == 0
    attn_head_dim: int = 16  # query/key width per head
    attn_max_in: int = 2000  # cap on in-mask anchors updated per step (GScream caps at 2000)
    attn_max_side: int = 2000  # cap on ring anchors attended to per step
    attn_mix: float = 1.0  # 1 = direct replacement (paper); < 1 = EMA blend with the old feature
    attn_write_back: bool = True  # store the attended features in the parameter after the step
    ring_frac: float = 0.5  # ring width as a fraction of the mask's bounding-box size ...
    ring_min_px: int = 4  # ... but at least this many pixels
    attn_from: float = 0.5  # fraction of the run before attention starts (GScream: 15k of 30k,
    #                         once anchor growth has stopped and the sets stay put); 0 = always
    attn_lr_init: float = 0.01  # query/key projections: GScream's log-linear schedule
    attn_lr_final: float = 1e-5  # ... its value at the run's end
    # -- reference depth loss
    depth_loss: bool = True
    lambda_depth: float = 10.0  # supplement: lambda_D = 10
    # Steps of the auxiliary GS trained on the captured images for the depth prior when the dataset
    # ships none (None: max(min(100, iters), iters // 5): a smoke run with a few steps stays quick).
    depth_prior_iters: int | None = None
    # -- background depth in every view's mask (`coin_cl.gs.background_depth`): removal
    #    only (an insertion's masks hold the new object, not the background)
    bg_depth: bool = True
    lambda_bg_depth: float = 3.0  # weight of the background depth term (>= 0; 0 = off)
    bg_depth_margin: float = 0.05  # relative band around D_bg left free
    bg_depth_behind: float = 0.1  # weight of the behind side (0: penalise only what is in front)
    # D_bg continues the planes around each mask (`coin_cl.gs.surface_planes`) where they pass in
    # front of its 2D fill; False: the 2D fill alone (the code before 2026-11-25)
    bg_depth_planes: bool = True
    # The depth terms' (reference depth, background depth) root-mean-square gradient held to at
    # most this times the photometric's, in Ref-GS and TE-D (`coin_cl.gs.balance`): each term then
    # holds at most ratio^2 (1 % at the default 0.1) of Adam's second moment. Uncapped, on the
    # cup_plain capture they filled it and blurred the whole view (Ref-GS alone, 1,375 steps: PSNR
    # outside the masks 27.27 uncapped, 27.95 at 1.0, 28.88 at 0.3; docs/BENCHMARKS.md "The depth
    # terms' share", where 0.1 is measured end to end). 0: uncapped.
    aux_grad_ratio: float = balance.RATIO
    # Growth may take the model to at least this many times its initial neural Gaussians, also where
    # the per-pixel cap (`ScaffoldStrategy.gaussians_per_pixel`) is below that: a scene whose sparse
    # points start above the cap (SPIn-NeRF scene 1: 0.11 per pixel) would otherwise never grow, and
    # the hole keeps the few anchors left after the object's points are pruned: a blur. Grown, the
    # gravel's grain crosses it (SPIn-NeRF at budget 10: m-PSNR 13.15 -> 13.24, masked VGG distance
    # 4.105 -> 3.892; docs/BENCHMARKS.md, "A floor over the initial size"). 1 = the per-pixel cap alone.
    growth_over_initial: float = 1.5
    # RNG seed of Ref-GS (model init, training, attention). None (default): the run's seed (`seed` of
    # `run_refgs`, `CoInConfig.seed` in a CoIn run; the resolved value is in log.json's 2_refgs settings).
    seed: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.prune_min_fraction <= 1.0:
            raise ValueError(f"prune_min_fraction must be in (0, 1], got {self.prune_min_fraction}")
        if self.prune_min_views < 1:
            raise ValueError(f"prune_min_views must be >= 1, got {self.prune_min_views}")
        if not (math.isfinite(self.lambda_r) and self.lambda_r > 0):
            raise ValueError(f"lambda_r must be a positive number, got {self.lambda_r}")
        if self.weight_region not in ("mask", "view"):
            raise ValueError(f"weight_region must be 'mask' or 'view', got {self.weight_region!r}")
        if not 0.0 <= self.first_visit_weight:
            raise ValueError(f"first_visit_weight must be >= 0, got {self.first_visit_weight}")
        if self.attn_heads < 1 or self.attn_head_dim < 1:
            raise ValueError("attn_heads and attn_head_dim must be >= 1")
        if self.attn_max_in < 1 or self.attn_max_side < 1:
            raise ValueError("attn_max_in and attn_max_side must be >= 1")
        if not 0.0 < self.attn_mix <= 1.0:
            raise ValueError(f"attn_mix must be in (0, 1], got {self.attn_mix}")
        if self.ring_frac < 0 or self.ring_min_px < 1:
            raise ValueError("ring_frac must be >= 0 and ring_min_px >= 1")
        if self.lambda_bg_depth < 0 or self.bg_depth_margin < 0 or self.bg_depth_behind < 0:
            raise ValueError("lambda_bg_depth, bg_depth_margin and bg_depth_behind must be >= 0")
        balance.check_ratio(self.aux_grad_ratio)
        if not (math.isfinite(self.growth_over_initial) and self.growth_over_initial >= 1.0):
            raise ValueError(f"RefGSConfig.growth_over_initial is {self.growth_over_initial!r}: give a "
                             "number >= 1 (1: the per-pixel cap alone)")  # fmt: skip
        if self.lambda_depth < 0:
            raise ValueError(f"lambda_depth must be >= 0, got {self.lambda_depth}")
        if not 0.0 <= self.attn_from <= 1.0:
            raise ValueError(f"attn_from must be in [0, 1], got {self.attn_from}")
        if not (self.attn_lr_init > 0 and self.attn_lr_final > 0):
            raise ValueError("attn_lr_init and attn_lr_final must be > 0")
        if self.seed is not None and not (isinstance(self.seed, int) and not isinstance(self.seed, bool)):
            raise ValueError(f"RefGSConfig.seed is {self.seed!r}: give an integer, or None (the run's)")
        if self.depth_prior_iters is not None and self.depth_prior_iters < 1:
            raise ValueError(f"RefGSConfig.depth_prior_iters is {self.depth_prior_iters!r}: give a step "
                             "count >= 1, or None")  # fmt: skip

    def attention_active(self, step: int, iters: int) -> bool:
        """Whether anchor attention runs at 0-based `step` of a run of `iters` steps."""
        return self.feature_attention and step >= self.attn_from * iters

    def attn_lr(self, iters: int) -> ExpSchedule:
        """Learning-rate schedule of the attention's parameters over a run of `iters` steps."""
        return ExpSchedule(self.attn_lr_init, self.attn_lr_final, iters)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> RefGSConfig:
        return RefGSConfig(**d)


def view_weights(cfg: RefGSConfig, ref_view: Any) -> AdaptiveViewWeights:
    """The adaptive view weights `cfg` asks for, with `ref_view` the reference's key."""
    return AdaptiveViewWeights(ref_view, cfg.lambda_r, cfg.first_visit_weight, cfg.adaptive_weights)


def anchor_attention(cfg: RefGSConfig, feat_dim: int = 32) -> AnchorAttention:
    """The anchor attention module `cfg` asks for, over features of width `feat_dim`."""
    return AnchorAttention(
        feat_dim,
        cfg.attn_heads,
        cfg.attn_head_dim,
        cfg.attn_max_in,
        cfg.attn_max_side,
        cfg.attn_mix,
        0 if cfg.seed is None else cfg.seed,  # None outside a run (`run_refgs` resolves it): 0
    )


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
    bg_depths: Sequence[np.ndarray | None] | None = None,
) -> list[LossTerm]:
    """Scaffold-GS's published loss plus Ref-GS's pieces, as `RefGSConfig` switches them.

    Always: `PhotometricLoss` (with `AdaptiveWeightSource`; constant 1 when
    `cfg.adaptive_weights` is off) and `ScaleVolumeReg`. `ReferenceDepthTerm` when
    `cfg.depth_loss` (needs `depth_prior` [H, W]); `BackgroundDepthTerm` when `cfg.bg_depth` and
    `bg_depths` (D_bg [H, W] or None per trainer view) are given; `AnchorAttentionTerm` when
    `cfg.feature_attention`.

    Args:
        ref_index: the reference's trainer view index; masks: [H, W] bool per trainer view.
        iters: the run's length (attention start and lr schedule).
    """
    weights = view_weights(cfg, ref_index)
    terms: list[LossTerm] = [
        PhotometricLoss(
            loss_cfg or LossConfig(),
            view_weights=AdaptiveWeightSource(weights),
            weighted_regions=masks if cfg.weight_region == "mask" else None,
        ),  # fmt: skip
        ScaleVolumeReg(),
    ]
    if cfg.depth_loss:
        if depth_prior is None:
            raise ValueError("cfg.depth_loss is on but no depth prior was given")
        terms.append(
            ReferenceDepthTerm(ref_index, depth_prior, masks[ref_index], cfg.lambda_depth, depth_is_disparity)
        )
    if cfg.bg_depth and bg_depths is not None:
        terms.append(background_depth_term(cfg, bg_depths, masks))
    if cfg.feature_attention:
        # attention_active(step, iters) is step >= attn_from * iters once feature_attention is on
        terms.append(AnchorAttentionTerm(anchor_attention(cfg, feat_dim), masks, cfg.attn_lr(iters),
                                         cfg.attn_from * iters, cfg.ring_frac, cfg.ring_min_px,
                                         cfg.attn_write_back))  # fmt: skip
    return terms


def background_depth_term(
    cfg: RefGSConfig, bg_depths: Sequence[np.ndarray | None], masks: Sequence[np.ndarray]
) -> BackgroundDepthTerm:
    """The background depth term with `cfg`'s settings (Ref-GS builds it; TE-D reuses it)."""
    return BackgroundDepthTerm(
        bg_depths, masks, cfg.lambda_bg_depth, cfg.bg_depth_margin, cfg.bg_depth_behind
    )


def adaptive_weights_of(terms: Sequence[LossTerm]) -> AdaptiveViewWeights | None:
    """The `AdaptiveViewWeights` inside a term list built by `refgs_terms` (None if absent)."""
    for t in terms:
        vw = getattr(t, "view_weights", None)
        if isinstance(vw, AdaptiveWeightSource):
            return vw.weights
    return None
