"""Ref-GS building blocks (CoIn paper section 4.2, issue 11): the reference-adaptive coarse stage.

Self-contained pieces the trainer plugs in; every one can be switched off through `RefGSConfig`
for the paper's ablations (Table 4: w/o adaptive weight, w/o feature attention, w/o Ref-GS).

* `composite_targets`: the training target of view n is its inpaint I^_n inside the mask and the
  captured image outside (paper 5.1).
* `prune_points_in_masks`: SfM points that project into the masks (in at least `min_fraction` of
  the views that see them) are removed before the anchors are built, so that the residual object
  in the COLMAP points cannot come back.
* `AdaptiveViewWeights`: the per-view loss weight W_n (lambda_r for the reference view k, a
  sigmoid of the change of the view's photometric loss since its previous visit for the others).
* `AnchorAttention` + `mask_anchor_sets`: anchors projected inside the current view's mask
  attend to anchors in a ring around it (unidirectional, every training view).
* `fit_affine` / `reference_depth_loss` / `reference_depth_prior`: the reference view's depth
  loss lambda_D * mean |A * R + B - D| with A, B a closed-form least-squares fit.
* `choose_reference` / `resolve_reference`: which view is the reference.

Intended use per run (the trainer wires it; nothing here touches the trainer):
    before: k = choose_reference(scene, ref=cfg.ref); targets = composite_targets per view;
            points = prune_points_in_masks(train cameras, train masks).points -> anchors;
            prior = reference_depth_prior(scene, k, ...)
    each step on view n (with its mask M_n):
        feats, info = attn.apply_view(features, anchors, cam_n, M_n)   if cfg.attention_active
        render with `feats` in place of the feature parameter (decode) -> image, depth
        L_R = photometric loss; W_n = weights.weight(n, L_R)
        loss = W_n * L_R (+ reference_depth_loss(depth, prior, M_k, disparity=...) when n == k)
        backward, optimizer steps (model and attention), then write_back_features if enabled
    checkpoint: weights.state_dict(), attn.state_dict() (generator state included).

Cameras are duck-typed: anything with `K` [3, 3], `viewmat` [4, 4] world-to-camera (OpenCV axes),
`width`, `height` (numpy or torch), such as `coin_cl.scene.types.Camera`. Pixel centres are at
+0.5, so a projection (u, v) lies in pixel (floor(v), floor(u)), as everywhere in the package.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from coin_cl.engine import constants as cst
from coin_cl.gs.optim import ExpSchedule

log = logging.getLogger(__name__)

DATASET_DEPTH_PRIOR = "dataset inpainted disparity (LaMa)"
GS_DEPTH_PRIOR = "GS depth of the unmasked scene, inpainted in 2D (cv2.inpaint Telea)"


@dataclass
class RefGSConfig:
    """Ref-GS switches and hyper-parameters (paper 4.2 and supplement C).

    Ablations: `adaptive_weights=False` (all views weight 1), `feature_attention=False`,
    `depth_loss=False`; all three plus `prune_points=False` is plain training on the inpaints.
    """

    # -- reference view: name or index (see `resolve_reference`); None = `choose_reference` rule
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
    attn_lr_final: float = 1e-5
    # -- reference depth loss
    depth_loss: bool = True
    lambda_depth: float = 10.0  # supplement: lambda_D = 10
    # Steps of the auxiliary GS trained on the captured images for the depth prior when the dataset
    # ships none (None: max(min(100, iters), iters // 5): a smoke run with a few steps stays quick).
    depth_prior_iters: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 < self.prune_min_fraction <= 1.0:
            raise ValueError(f"prune_min_fraction must be in (0, 1], got {self.prune_min_fraction}")
        if self.prune_min_views < 1:
            raise ValueError(f"prune_min_views must be >= 1, got {self.prune_min_views}")
        if not (math.isfinite(self.lambda_r) and self.lambda_r > 0):
            raise ValueError(f"lambda_r must be a positive number, got {self.lambda_r}")
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
        if self.lambda_depth < 0:
            raise ValueError(f"lambda_depth must be >= 0, got {self.lambda_depth}")
        if not 0.0 <= self.attn_from <= 1.0:
            raise ValueError(f"attn_from must be in [0, 1], got {self.attn_from}")
        if not (self.attn_lr_init > 0 and self.attn_lr_final > 0):
            raise ValueError("attn_lr_init and attn_lr_final must be > 0")

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


# ---------------------------------------------------------------------------------------------
# cameras and projection


def _cam_arrays(cam: Any) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(K [3,3], viewmat [4,4]) float64 numpy, width, height of any camera-like object."""
    K = np.asarray(cam.K.detach().cpu() if isinstance(cam.K, Tensor) else cam.K, np.float64)
    V = cam.viewmat
    V = np.asarray(V.detach().cpu() if isinstance(V, Tensor) else V, np.float64)
    if K.shape != (3, 3) or V.shape != (4, 4):
        raise ValueError(f"camera needs K [3,3] and viewmat [4,4], got {K.shape} and {V.shape}")
    return K, V, int(cam.width), int(cam.height)


def project_pixels(points: np.ndarray | Tensor, cam: Any) -> tuple[np.ndarray, np.ndarray]:
    """Pixels hit by world points.

    Args:
        points: [P, 3] world positions.
        cam: camera-like (see module doc).
    Returns:
        (px [P, 2] int64 (column, row), ok [P] bool): ok = in front of the camera (camera z above
        the renderer's near plane, so exactly what could be drawn) and inside the image; px is
        only meaningful where ok.
    """
    K, V, W, H = _cam_arrays(cam)
    p = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    p = np.asarray(p, np.float64).reshape(-1, 3)
    pc = p @ V[:3, :3].T + V[:3, 3]
    z = pc[:, 2]
    front = z > cst.NEAR_PLANE
    zs = np.where(front, z, 1.0)  # avoid dividing by ~0 behind the camera; masked out below
    uv = (pc[:, :2] / zs[:, None]) @ K[:2, :2].T + K[:2, 2]
    with np.errstate(invalid="ignore"):
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    ok = front & inside & np.isfinite(uv).all(1)
    px = np.zeros((len(p), 2), np.int64)
    px[ok] = np.floor(uv[ok]).astype(np.int64)
    # floor(u) can equal W only through rounding at the border; keep the index valid.
    px[:, 0] = np.clip(px[:, 0], 0, W - 1)
    px[:, 1] = np.clip(px[:, 1], 0, H - 1)
    return px, ok


def _check_mask(mask: Any, H: int, W: int, what: str) -> np.ndarray:
    m = np.asarray(mask.detach().cpu() if isinstance(mask, Tensor) else mask)
    if m.shape != (H, W):
        raise ValueError(f"{what}: mask is {m.shape} but the camera is {H}x{W} (rows x columns)")
    return m.astype(bool)


# ---------------------------------------------------------------------------------------------
# 1. targets


def composite_targets(inpainted: Any, image: Any, mask: Any) -> Any:
    """The Ref-GS target: the inpaint I^_n inside the mask, the captured image outside.

    The inpainter may alter pixels it was not asked to change (colour shifts, VAE round trips);
    the captured pixels outside the mask are ground truth, so they win (paper 5.1).

    Args:
        inpainted, image: [H, W, 3] float, both numpy or both torch.
        mask: [H, W] bool, True = region to inpaint.
    Returns:
        [H, W, 3], same type and dtype as `inpainted`.
    """
    if tuple(inpainted.shape) != tuple(image.shape) or inpainted.ndim != 3:
        raise ValueError(
            f"inpainted {tuple(inpainted.shape)} and image {tuple(image.shape)} must both be [H, W, C]"
        )
    H, W = inpainted.shape[:2]
    if isinstance(inpainted, Tensor):
        m = torch.as_tensor(_check_mask(mask, H, W, "composite_targets"), device=inpainted.device)
        return torch.where(m[..., None], inpainted, image.to(inpainted.dtype))
    m = _check_mask(mask, H, W, "composite_targets")
    return np.where(m[..., None], inpainted, np.asarray(image, dtype=np.asarray(inpainted).dtype))


# ---------------------------------------------------------------------------------------------
# 2. pruning


class PruneResult(NamedTuple):
    """points [M, 3] kept, n_removed, keep [P] bool over the input points (to slice colours)."""

    points: np.ndarray
    n_removed: int
    keep: np.ndarray


def mask_vote_counts(
    points: np.ndarray, cameras: Sequence[Any], masks: Sequence[Any]
) -> tuple[np.ndarray, np.ndarray]:
    """For points [P, 3]: in how many views each is seen (in front, inside the image) [P] int,
    and in how many of those its pixel is inside that view's mask [P] int."""
    if len(cameras) != len(masks):
        raise ValueError(f"{len(cameras)} cameras but {len(masks)} masks")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    seen = np.zeros(len(pts), np.int64)
    inside = np.zeros(len(pts), np.int64)
    for i, (cam, mask) in enumerate(zip(cameras, masks)):
        _, _, W, H = _cam_arrays(cam)
        m = _check_mask(mask, H, W, f"view {i}")
        px, ok = project_pixels(pts, cam)
        seen += ok
        inside += ok & m[px[:, 1], px[:, 0]]
    return seen, inside


def prune_points_in_masks(
    points: np.ndarray,
    cameras: Sequence[Any],
    masks: Sequence[Any],
    min_fraction: float = 0.5,
    min_views: int = 1,
) -> PruneResult:
    """Remove SfM points that fall inside the masks.

    A point is removed when it is seen (in front of the camera, inside the image) by at least
    `min_views` of the given views and its pixel is inside the mask in at least `min_fraction` of
    those views. Points seen by fewer views are kept: nothing says they are on the object.
    The default 0.5 (a majority) removes points on the object, which are inside the mask from
    every view, but keeps background points that the object hides only from some views.

    Args:
        points: [P, 3] world positions.
        cameras, masks: the views to vote with (normally the training views) and their [H, W] bool
            masks, aligned.
    Returns:
        PruneResult(points [M, 3] (same dtype as the input), n_removed, keep [P] bool).
    """
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be [P, 3], got {pts.shape}")
    seen, inside = mask_vote_counts(pts, cameras, masks)
    remove = (seen >= max(1, min_views)) & (inside >= min_fraction * seen)
    keep = ~remove
    return PruneResult(pts[keep], int(remove.sum()), keep)


# ---------------------------------------------------------------------------------------------
# 3. adaptive view weights


def stable_sigmoid(x: float) -> float:
    """1 / (1 + exp(-x)) without overflow: exp only ever sees a non-positive argument, so huge
    |x| gives exactly 0.0 or 1.0 and never NaN."""
    if x >= 0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


class AdaptiveViewWeights:
    """The paper's per-view loss weight W_n (eq. in 4.2).

    W_k = lambda_r for the reference view k; for any other view n
    W_n = 1 / (1 + exp(lambda_r * (L(n, t) - L(n, t-1)))) = sigmoid(-lambda_r * dL), where L(n, t)
    is the view's photometric loss now and L(n, t-1) its loss the previous time it was drawn. A
    view whose loss rose since its last visit (it disagrees with what the other views, led by the
    reference, have built) is down-weighted; one whose loss fell is up-weighted towards 1.

    First visit (no previous loss): `first_visit_weight`, default 0.5 = sigmoid(0), the value the
    formula gives to an unchanged loss, so the first pass neither favours nor punishes a view.
    With `enabled=False` (ablation "w/o adaptive weight") every view, the reference included,
    gets weight 1.0; losses and history are still recorded.

    `weight(view, loss)` must be called once per visit, with the view's unweighted photometric
    loss (a float) before the backward pass; it updates the state. Views are any hashable keys
    (the trainer's view indices).
    """

    def __init__(
        self,
        ref_view: Any,
        lambda_r: float = 50.0,
        first_visit_weight: float = 0.5,
        enabled: bool = True,
    ):
        if not (math.isfinite(lambda_r) and lambda_r > 0):
            raise ValueError(f"lambda_r must be a positive number, got {lambda_r}")
        self.ref_view = ref_view
        self.lambda_r = float(lambda_r)
        self.first_visit_weight = float(first_visit_weight)
        self.enabled = bool(enabled)
        self.prev: dict[Any, float] = {}
        self.history: list[dict[str, Any]] = []

    @staticmethod
    def from_config(cfg: RefGSConfig, ref_view: Any) -> AdaptiveViewWeights:
        return AdaptiveViewWeights(ref_view, cfg.lambda_r, cfg.first_visit_weight, cfg.adaptive_weights)

    def formula(self, loss_now: float, loss_prev: float) -> float:
        """sigmoid(-lambda_r * (loss_now - loss_prev)) for a non-reference view."""
        return stable_sigmoid(-self.lambda_r * (loss_now - loss_prev))

    def weight(self, view: Any, loss_now: float | Tensor, step: int | None = None) -> float:
        """The weight of `view` for this visit (and record `loss_now` as its latest loss)."""
        loss = float(loss_now.detach()) if isinstance(loss_now, Tensor) else float(loss_now)
        if not math.isfinite(loss):
            raise ValueError(
                f"view {view!r}: photometric loss is {loss} at step {step}; adaptive weights need a "
                "finite loss (the run has diverged or the target holds NaN/Inf)"
            )
        prev = self.prev.get(view)
        if not self.enabled:
            w = 1.0
        elif view == self.ref_view:
            w = self.lambda_r
        elif prev is None:
            w = self.first_visit_weight
        else:
            w = self.formula(loss, prev)
        self.prev[view] = loss
        self.history.append({"step": step, "view": view, "loss": loss, "prev": prev, "weight": w})
        return w

    def summary(self) -> dict[Any, dict[str, float]]:
        """Per view: visits, mean and last weight (for the JSON log's digest)."""
        out: dict[Any, dict[str, float]] = {}
        for h in self.history:
            s = out.setdefault(h["view"], {"visits": 0, "mean_weight": 0.0, "last_weight": 0.0})
            s["visits"] += 1
            s["mean_weight"] += h["weight"]
            s["last_weight"] = h["weight"]
        for s in out.values():
            s["mean_weight"] /= s["visits"]
        return out

    def state_dict(self) -> dict[str, Any]:
        """Everything needed for a bit-exact resume (plain Python floats: exact in torch.save)."""
        return {
            "ref_view": self.ref_view,
            "lambda_r": self.lambda_r,
            "first_visit_weight": self.first_visit_weight,
            "enabled": self.enabled,
            "prev": dict(self.prev),
            "history": [dict(h) for h in self.history],
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.ref_view = sd["ref_view"]
        self.lambda_r = float(sd["lambda_r"])
        self.first_visit_weight = float(sd["first_visit_weight"])
        self.enabled = bool(sd["enabled"])
        self.prev = dict(sd["prev"])
        self.history = [dict(h) for h in sd["history"]]


# ---------------------------------------------------------------------------------------------
# 4. anchor feature attention


def ring_mask(mask: np.ndarray, width_px: float) -> np.ndarray:
    """[H, W] bool: pixels outside `mask` within `width_px` (Euclidean) of it."""
    m = np.asarray(mask, bool)
    if not m.any():
        return np.zeros_like(m)
    # Distance of every non-mask pixel to the nearest mask pixel (mask pixels get 0).
    dist = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return (dist <= width_px) & ~m


def ring_width_px(mask: np.ndarray, ring_frac: float = 0.5, ring_min_px: int = 4) -> float:
    """Ring width: `ring_frac` x the larger side of the mask's bounding box, at least
    `ring_min_px`; so the ring scales with the hole and holds about as many anchors as it."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float(ring_min_px)
    ys = np.flatnonzero(m.any(1))
    xs = np.flatnonzero(m.any(0))
    size = max(ys[-1] - ys[0] + 1, xs[-1] - xs[0] + 1)
    return float(max(ring_min_px, ring_frac * size))


def mask_anchor_sets(
    anchors: np.ndarray | Tensor,
    cam: Any,
    mask: Any,
    ring_frac: float = 0.5,
    ring_min_px: int = 4,
) -> tuple[Tensor, Tensor]:
    """Anchors inside the view's mask and in a ring around it.

    An anchor counts when its centre is in front of the camera and projects inside the image;
    then it is 'in' when its pixel is in the mask and 'side' when its pixel is in the ring
    (`ring_mask` with `ring_width_px`). Occlusion is not tested: anchors behind the masked object
    are exactly the ones to fill.

    Args:
        anchors: [A, 3] anchor centres.
        cam: camera-like; mask: [H, W] bool of that view.
    Returns:
        (in_idx [I] int64, side_idx [S] int64) ascending anchor indices, disjoint.
    """
    _, _, W, H = _cam_arrays(cam)
    m = _check_mask(mask, H, W, "mask_anchor_sets")
    px, ok = project_pixels(anchors, cam)
    ring = ring_mask(m, ring_width_px(m, ring_frac, ring_min_px))
    r, c = px[:, 1], px[:, 0]
    in_sel = ok & m[r, c]
    side_sel = ok & ring[r, c]
    return torch.from_numpy(np.flatnonzero(in_sel)), torch.from_numpy(np.flatnonzero(side_sel))


class AnchorAttention(nn.Module):
    """Unidirectional multi-head attention from in-mask anchors to ring anchors (paper 4.2):
    f_in <- Attn(Q = f_in, K = f_side, V = f_side).

    Design (compared with GScream, which runs bidirectional cross-attention with learned value
    and output projections, only in the reference view, and also rewrites the side features):
    * Only f_in changes; side features and every other anchor are returned untouched.
    * Queries and keys are learned projections (`heads` x `head_dim`), scaled dot product.
    * Values are the side features themselves, split channel-wise into `heads` groups of
      feat_dim / heads (no value or output projection). Each head's output is therefore a convex
      combination of the side anchors' features in its channels: the in-mask anchors inherit
      appearance that exists around the hole instead of a learned remapping of it, and with
      identical side features the result is exactly that feature whatever the weights.
    * Update: f_in <- mix * Attn + (1 - mix) * f_in; the default mix = 1 is the paper's direct
      replacement (GScream's `ema` = 1); mix < 1 is an EMA-style blend. No residual: a residual
      would add the neighbourhood on top of whatever the inconsistent inpaints put there.
    * Caps: at most `max_in` query anchors and `max_side` key anchors per call, drawn uniformly
      without replacement by the module's own seeded generator (its state is saved in
      `state_dict` through `get_extra_state`); in-mask anchors not drawn keep their feature this
      call and are drawn in later ones.
    * Empty in- or side set: nothing to do; the features come back unchanged (same tensor), the
      call is counted in `n_skipped` and logged at debug level, and `info['skipped']` says why.

    Gradients flow to the query/key projections (through the attention weights), to the side
    features (values and keys) and to the in features (queries).
    """

    def __init__(
        self,
        feat_dim: int = 32,
        heads: int = 4,
        head_dim: int = 16,
        max_in: int = 2000,
        max_side: int = 2000,
        mix: float = 1.0,
        seed: int = 0,
    ):
        super().__init__()
        if feat_dim % heads:
            raise ValueError(f"feat_dim {feat_dim} must be divisible by heads {heads}")
        if not 0.0 < mix <= 1.0:
            raise ValueError(f"mix must be in (0, 1], got {mix}")
        self.feat_dim, self.heads, self.head_dim = feat_dim, heads, head_dim
        self.max_in, self.max_side, self.mix = int(max_in), int(max_side), float(mix)
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            self.q = nn.Linear(feat_dim, heads * head_dim)
            self.k = nn.Linear(feat_dim, heads * head_dim)
        self.gen = torch.Generator().manual_seed(seed + 1)
        self.n_calls = 0
        self.n_skipped = 0

    @staticmethod
    def from_config(cfg: RefGSConfig, feat_dim: int = 32) -> AnchorAttention:
        return AnchorAttention(
            feat_dim, cfg.attn_heads, cfg.attn_head_dim, cfg.attn_max_in, cfg.attn_max_side,
            cfg.attn_mix, cfg.seed,
        )  # fmt: skip

    def get_extra_state(self) -> dict[str, Any]:
        return {"gen": self.gen.get_state(), "n_calls": self.n_calls, "n_skipped": self.n_skipped}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.gen.set_state(state["gen"])
        self.n_calls = int(state["n_calls"])
        self.n_skipped = int(state["n_skipped"])

    def _subsample(self, idx: Tensor, cap: int) -> Tensor:
        if idx.numel() <= cap:
            return idx
        pick = torch.randperm(idx.numel(), generator=self.gen)[:cap]
        return idx[pick.sort().values]

    def attend(self, f_in: Tensor, f_side: Tensor) -> Tensor:
        """Attn(Q = f_in [I, C], K = V = f_side [S, C]) -> [I, C] (before the mix)."""
        h, d, c = self.heads, self.head_dim, self.feat_dim
        q = self.q(f_in).view(-1, h, d).transpose(0, 1)  # [h, I, d]
        k = self.k(f_side).view(-1, h, d).transpose(0, 1)  # [h, S, d]
        v = f_side.view(-1, h, c // h).transpose(0, 1)  # [h, S, C/h]
        w = torch.softmax(q @ k.transpose(1, 2) / math.sqrt(d), dim=-1)  # [h, I, S]
        return (w @ v).transpose(0, 1).reshape(-1, c)

    def forward(self, features: Tensor, in_idx: Tensor, side_idx: Tensor) -> tuple[Tensor, dict[str, Any]]:
        """Features with the in-mask rows attended.

        Args:
            features: [A, C] anchor features (the parameter; not modified in place).
            in_idx: [I] int64 indices of in-mask anchors; side_idx: [S] int64 ring anchors.
        Returns:
            (features' [A, C], info {'n_in', 'n_side', 'n_in_used', 'n_side_used', 'skipped',
            'updated' [I'] int64 indices actually replaced}).
        """
        if features.dim() != 2 or features.shape[1] != self.feat_dim:
            raise ValueError(f"features must be [A, {self.feat_dim}], got {tuple(features.shape)}")
        in_idx = torch.as_tensor(in_idx, dtype=torch.long).reshape(-1)
        side_idx = torch.as_tensor(side_idx, dtype=torch.long).reshape(-1)
        a = features.shape[0]
        for name, idx in (("in_idx", in_idx), ("side_idx", side_idx)):
            if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= a):
                raise IndexError(f"{name} out of range for {a} anchors")
        self.n_calls += 1
        info: dict[str, Any] = {"n_in": int(in_idx.numel()), "n_side": int(side_idx.numel()),
                                "n_in_used": 0, "n_side_used": 0, "skipped": None,
                                "updated": in_idx[:0]}  # fmt: skip
        if in_idx.numel() == 0 or side_idx.numel() == 0:
            empty_in = in_idx.numel() == 0
            info["skipped"] = "no anchors inside the mask" if empty_in else "no anchors in the ring"
            self.n_skipped += 1
            log.debug("anchor attention skipped: %s", info["skipped"])
            return features, info
        if bool(torch.isin(in_idx, side_idx).any()):
            raise ValueError("in_idx and side_idx overlap; an anchor is either in the mask or in the ring")
        qi = self._subsample(in_idx, self.max_in)
        si = self._subsample(side_idx, self.max_side)
        f_in = features[qi]
        new = self.attend(f_in, features[si])
        if self.mix < 1.0:
            new = self.mix * new + (1.0 - self.mix) * f_in
        out = features.index_copy(0, qi, new.to(features.dtype))
        info.update(n_in_used=int(qi.numel()), n_side_used=int(si.numel()), updated=qi)
        return out, info

    def apply_view(
        self,
        features: Tensor,
        anchors: np.ndarray | Tensor,
        cam: Any,
        mask: Any,
        ring_frac: float = 0.5,
        ring_min_px: int = 4,
    ) -> tuple[Tensor, dict[str, Any]]:
        """`mask_anchor_sets` then `forward`, for one training view.

        Args:
            features: [A, C]; anchors: [A, 3] their centres; cam, mask [H, W] bool: the view.
        Returns:
            as `forward`.
        """
        in_idx, side_idx = mask_anchor_sets(anchors, cam, mask, ring_frac, ring_min_px)
        return self(features, in_idx, side_idx)


@torch.no_grad()
def write_back_features(param: Tensor, attended: Tensor, updated: Tensor) -> None:
    """Store the attended rows in the feature parameter (after the optimizer step), so that
    evaluation, export and the next views see them (`RefGSConfig.attn_write_back`).

    Args:
        param: [A, C] the model's feature parameter; attended: [A, C] the forward's output;
        updated: [I] int64 rows that were replaced (`info['updated']`).
    The Adam moments of those rows are kept: they describe the same feature slot.
    """
    if updated.numel():
        param.index_copy_(0, updated, attended.detach()[updated].to(param.dtype))


# ---------------------------------------------------------------------------------------------
# 5. reference depth loss


def fit_affine(render_depth: Tensor, prior: Tensor, valid: Tensor | None = None) -> tuple[float, float]:
    """Least-squares (A, B) minimising sum over valid pixels of (A * render + B - prior)^2.

    Closed form in float64 with no gradient (the fit is a fixed target for this step).
    * A may be negative: a disparity prior falls where depth rises.
    * Constant render depth over the valid pixels (singular normal equations, relative variance
      below 1e-12): A = 0, B = mean(prior), the best constant; the loss is then finite and gives
      the render no gradient through A.
    * Non-finite pixels (in either map) are left out of the fit.

    Args:
        render_depth, prior: [H, W]; valid: [H, W] bool (default all pixels).
    Returns:
        (A, B) Python floats.
    Raises:
        ValueError when no valid finite pixel remains.
    """
    r = render_depth.detach().to(torch.float64).reshape(-1)
    d = torch.as_tensor(prior).detach().to(torch.float64).reshape(-1)
    if r.shape != d.shape:
        raise ValueError(f"render depth {tuple(render_depth.shape)} and prior {tuple(prior.shape)} differ")
    ok = torch.isfinite(r) & torch.isfinite(d)
    if valid is not None:
        v = torch.as_tensor(valid).reshape(-1).bool()
        if v.shape != r.shape:
            raise ValueError(f"valid {tuple(valid.shape)} does not match depth {tuple(render_depth.shape)}")
        ok &= v
    n = int(ok.sum())
    if n == 0:
        raise ValueError("fit_affine: no valid finite pixel to fit the depth prior on")
    r, d = r[ok], d[ok]
    # Centred normal equations: A = cov(r, d) / var(r), B = mean(d) - A mean(r) (stable in f64).
    rm, dm = r.mean(), d.mean()
    var = ((r - rm) ** 2).mean()
    if float(var) <= 1e-12 * max(float(rm * rm), 1e-30):
        return 0.0, float(dm)
    a = ((r - rm) * (d - dm)).mean() / var
    return float(a), float(dm - a * rm)


def reference_depth_loss(
    render_depth: Tensor,
    prior: Tensor,
    mask: Tensor | np.ndarray,
    lambda_d: float = 10.0,
    valid: Tensor | None = None,
    disparity: bool = False,
) -> tuple[Tensor, dict[str, float]]:
    """lambda_D * mean over the reference view of |A * R + B - D| (paper 4.2, L_D).

    The fit (A, B) uses the pixels outside the mask (where the render is supervised by the
    captured image, so it is a fair ruler); the L1 then runs over the whole view (the paper's
    1/HW sum), which is what pulls the geometry inside the hole towards the prior.

    Args:
        render_depth: [H, W] rendered expected depth (gradient flows into it).
        prior: [H, W] depth prior D_k (any affine-related quantity: relative depth, disparity).
        mask: [H, W] bool, True = inpainted region (left out of the fit).
        valid: optional [H, W] bool of usable pixels (for instance rendered alpha > 0.5); pixels
            outside it are in neither the fit nor the mean.
        disparity: the prior is a disparity (the dataset's LaMa depth): the render is turned into
            disparity 1 / max(R, near plane) first, so the fit is in the prior's space, where an
            affine relation actually holds.
    Returns:
        (loss scalar, {'A', 'B', 'n_fit'}). If the mask leaves no pixel to fit on, the fit falls
        back to all valid pixels (logged).
    """
    if render_depth.dim() != 2:
        raise ValueError(f"render depth must be [H, W], got {tuple(render_depth.shape)}")
    H, W = render_depth.shape
    m = torch.as_tensor(_check_mask(mask, H, W, "reference_depth_loss"), device=render_depth.device)
    d = torch.as_tensor(prior, dtype=render_depth.dtype, device=render_depth.device)
    if tuple(d.shape) != (H, W):
        raise ValueError(f"prior is {tuple(d.shape)} but the render depth is {(H, W)}")
    r = 1.0 / render_depth.clamp_min(cst.NEAR_PLANE) if disparity else render_depth
    ok = torch.isfinite(r) & torch.isfinite(d)
    if valid is not None:
        ok &= torch.as_tensor(valid, device=r.device).bool()
    # Zero the unusable pixels before any arithmetic: `where` then passes them an exact zero
    # gradient, whereas masking the error afterwards would multiply 0 by NaN in the backward.
    r = torch.where(ok, r, torch.zeros_like(r))
    d = torch.where(ok, d, torch.zeros_like(d))
    fit_px = ok & ~m
    if not bool(fit_px.any()):
        log.warning("reference depth loss: no valid pixel outside the mask; fitting on the whole view")
        fit_px = ok
    a, b = fit_affine(r, d, fit_px)
    err = torch.where(ok, (a * r + b - d).abs(), torch.zeros_like(r))
    loss = lambda_d * err.sum() / ok.sum().clamp_min(1)
    return loss, {"A": a, "B": b, "n_fit": int(fit_px.sum())}


class DepthPrior(NamedTuple):
    """prior [H, W] float32 and the name of its source (logged). Unpacks as (prior, name)."""

    prior: np.ndarray
    name: str

    @property
    def is_disparity(self) -> bool:
        """True when the prior is a disparity (pass as `reference_depth_loss(disparity=...)`)."""
        return self.name == DATASET_DEPTH_PRIOR


def inpaint_depth(depth: np.ndarray, mask: np.ndarray, radius: int = 5) -> np.ndarray:
    """Fill `mask` [H, W] bool of a depth map [H, W] with cv2.inpaint (Telea).

    OpenCV 5's Telea on float32 is wrong (a constant image does not stay constant), so the depth
    is quantised to 16 bits over its finite range, inpainted and mapped back; the error is at most
    range / 65535. Non-finite pixels are inpainted too. Returns [H, W] float32.
    """
    d = np.asarray(depth, np.float64)
    hole = np.asarray(mask, bool) | ~np.isfinite(d)
    known = d[~hole]
    if known.size == 0:
        raise ValueError("inpaint_depth: every pixel is masked or non-finite; nothing to inpaint from")
    lo, hi = float(known.min()), float(known.max())
    if hi - lo <= 0:
        return np.full(d.shape, lo, np.float32)
    q = np.round((np.where(hole, lo, d) - lo) / (hi - lo) * 65535).astype(np.uint16)
    out = cv2.inpaint(q, hole.astype(np.uint8), radius, cv2.INPAINT_TELEA)
    res = out.astype(np.float64) / 65535 * (hi - lo) + lo
    res[~hole] = d[~hole]  # keep the known pixels bit-exact
    return res.astype(np.float32)


def reference_depth_prior(
    scene: Any,
    ref_index: int,
    gs_depth: np.ndarray | Tensor | None = None,
    mask: np.ndarray | None = None,
) -> DepthPrior:
    """The depth prior D_k for the reference view, first available of:

    1. the dataset's inpainted disparity `scene.priors['depth'][ref_index]` (SPIn-NeRF's
       `Depth_inpainted/`, LaMa): name `DATASET_DEPTH_PRIOR`, a disparity;
    2. `gs_depth` [H, W], the caller's depth render of a GS trained on the unmasked scene, with
       the mask (default the scene's mask of that view) filled by `inpaint_depth`: name
       `GS_DEPTH_PRIOR`, a depth.
    A monocular estimator (Depth Anything) is not offered here.

    Raises:
        ValueError naming what is missing when neither source is available.
    """
    priors = getattr(scene, "priors", None) or {}
    dp = priors.get("depth", {})
    if ref_index in dp and dp[ref_index] is not None:
        return DepthPrior(np.asarray(dp[ref_index], np.float32), DATASET_DEPTH_PRIOR)
    if gs_depth is not None:
        g = gs_depth.detach().cpu().numpy() if isinstance(gs_depth, Tensor) else np.asarray(gs_depth)
        if mask is None:
            masks = getattr(scene, "masks", None)
            if masks is None:
                raise ValueError("reference_depth_prior: pass `mask`; the scene has no masks")
            mask = masks[ref_index]
        m = np.asarray(mask, bool)
        if m.shape != g.shape:
            raise ValueError(f"GS depth {g.shape} and mask {m.shape} differ")
        return DepthPrior(inpaint_depth(g, m), GS_DEPTH_PRIOR)
    raise ValueError(
        f"no depth prior for reference view {ref_index}: the scene has no Depth_inpainted prior for it "
        "and no GS depth render was given (train a GS on the unmasked scene and pass its depth)"
    )


# ---------------------------------------------------------------------------------------------
# 6. reference view


def reference_score(mask: np.ndarray) -> float:
    """Score of a view as reference: area fraction of its mask x centrality, where centrality =
    1 - |mask centroid - image centre| / half the image diagonal (1 at the centre, 0 in a
    corner). A large hole seen head-on gives the reference the most content to impose; a
    central one keeps that content in view of the neighbouring cameras. Empty mask: 0."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 0.0
    H, W = m.shape
    ys, xs = np.nonzero(m)
    # Pixel centres at +0.5, image centre at (W/2, H/2).
    dist = math.hypot(xs.mean() + 0.5 - W / 2, ys.mean() + 0.5 - H / 2)
    centrality = 1.0 - dist / (0.5 * math.hypot(W, H))
    return float(m.mean() * centrality)


def resolve_reference(ref: str | int, names: Sequence[str], candidates: Sequence[int]) -> int:
    """The view index that `--ref` names.

    Args:
        ref: an int index, a string of digits (an index), or a view name (with or without its
            extension).
        names: name of every view; candidates: indices allowed (the training views).
    Raises:
        ValueError with the allowed values when `ref` is unknown or not a training view.
    """
    cands = list(candidates)
    if isinstance(ref, bool) or not isinstance(ref, int | str | np.integer):
        raise ValueError(f"--ref must be a view name or index, got {ref!r}")
    idx: int | None = None
    if isinstance(ref, int | np.integer):
        idx = int(ref)
    else:
        s = ref.strip()
        stems = [n.rsplit(".", 1)[0] if "." in n else n for n in names]
        key = s.rsplit(".", 1)[0] if "." in s else s
        hits = [i for i, n in enumerate(names) if n == s] or [i for i, st in enumerate(stems) if st == key]
        if hits:
            idx = hits[0]
            # "12" naming view "12.png" while index 12 is another training view: say both readings.
            if s.isdigit() and s == str(int(s)) and int(s) in cands and int(s) != idx:
                raise ValueError(
                    f"--ref {ref!r} is ambiguous: the view named {names[idx]!r} (index {idx}) or the view at "
                    f"index {int(s)} ({names[int(s)]!r}); give the name with its extension, or the index "
                    "as an int from Python"
                )
        elif s.lstrip("-").isdigit():
            idx = int(s)
    shown = ", ".join(f"{i} ({names[i]})" for i in cands[:12]) + (" ..." if len(cands) > 12 else "")
    if idx is None:
        raise ValueError(f"--ref {ref!r}: no view of that name; training views: {shown}")
    if idx not in cands:
        raise ValueError(f"--ref {ref!r}: view {idx} is not a training view; training views: {shown}")
    return idx


def choose_reference(
    scene_or_masks: Any,
    cameras: Sequence[Any] | None = None,
    *,
    train_idx: Sequence[int] | None = None,
    ref: str | int | None = None,
) -> int:
    """The reference view k.

    With `ref` (the `--ref` option): `resolve_reference`. Otherwise the training view with the
    highest `reference_score` (largest, most central mask); ties go to the lowest index.

    Args:
        scene_or_masks: a Scene (masks, cameras, train_idx taken from it) or a sequence of
            [H, W] bool masks (one per view).
        cameras: camera-likes aligned with the masks (used for names); taken from the scene.
        train_idx: candidate views (default the scene's training views, else all views).
    Returns:
        the view index.
    """
    if hasattr(scene_or_masks, "masks"):
        masks = list(scene_or_masks.masks)
        cameras = list(scene_or_masks.cameras) if cameras is None else list(cameras)
        if train_idx is None and getattr(scene_or_masks, "train_idx", None):
            train_idx = list(scene_or_masks.train_idx)
    else:
        masks = list(scene_or_masks)
    if not masks:
        raise ValueError("choose_reference: no views")
    cands = list(range(len(masks))) if train_idx is None else [int(i) for i in train_idx]
    if not cands:
        raise ValueError("choose_reference: no candidate (training) views")
    if cameras is not None and len(cameras) != len(masks):
        raise ValueError(f"{len(cameras)} cameras but {len(masks)} masks")
    names = (
        [str(getattr(c, "name", "") or i) for i, c in enumerate(cameras)]
        if cameras
        else [str(i) for i in range(len(masks))]
    )
    if ref is not None:
        return resolve_reference(ref, names, cands)
    scores = [reference_score(masks[i]) for i in cands]
    best = cands[int(np.argmax(scores))]  # argmax returns the first maximum: lowest index wins
    if scores[cands.index(best)] == 0.0:
        log.warning("choose_reference: every candidate mask is empty; using view %d", best)
    return best
