"""Anchor feature attention (CoIn paper 4.2, Ref-GS): anchors projected inside the current
view's mask attend to anchors in a ring around it (unidirectional, every training view);
`AnchorAttentionTerm` runs it inside the trainer (`coin_cl.gs.terms` protocol).

Cameras are duck-typed (K [3, 3], viewmat [4, 4] world-to-camera, width, height; see
`coin_cl.scene.types.Camera.from_any`). An anchor is seen where its centre lies beyond the
renderer's near plane and inside the image (`Camera.pixels`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from coin_cl.engine import constants as cst
from coin_cl.gs.base import Model
from coin_cl.gs.data import View
from coin_cl.gs.optim import ExpSchedule
from coin_cl.gs.terms import LossContext, LossTerm
from coin_cl.scene.masks import mask_of_shape
from coin_cl.scene.types import Camera

log = logging.getLogger(__name__)


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
    cam = cam if isinstance(cam, Camera) else Camera.from_any(cam)
    m = mask_of_shape(mask, cam.height, cam.width, "mask_anchor_sets")
    px, ok = cam.pixels(anchors, near=cst.NEAR_PLANE)
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
        """Attn(Q = f_in [I, C], K = V = f_side [S, C]) -> [I, C] (before the mix): per head
        softmax(q k^T / sqrt(head_dim)) v, computed by torch's fused attention, which never holds
        the [heads, I, S] weights (`attend_written_out` does; error against it and both run times:
        `benchmarks/attention.py`)."""
        h, d, c = self.heads, self.head_dim, self.feat_dim
        q = self.q(f_in).view(-1, h, d).transpose(0, 1)[None]  # [1, h, I, d]
        k = self.k(f_side).view(-1, h, d).transpose(0, 1)[None]  # [1, h, S, d]
        v = f_side.view(-1, h, c // h).transpose(0, 1)[None]  # [1, h, S, C/h]
        # The fused kernels take one width for q, k and v: zero channels change neither the dot
        # products (the scale stays head_dim's) nor the output channels kept.
        e = max(d, c // h)
        q, k, v = (nn.functional.pad(t, (0, e - t.shape[-1])) for t in (q, k, v))
        o = nn.functional.scaled_dot_product_attention(q, k, v, scale=1.0 / math.sqrt(d))
        return o[0, ..., : c // h].transpose(0, 1).reshape(-1, c)

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


def attend_written_out(att: AnchorAttention, f_in: Tensor, f_side: Tensor) -> Tensor:
    """`att.attend` with its [heads, I, S] softmax weights written out and held: its reference (run
    in float64 by the tests and the benchmark)."""
    h, d, c = att.heads, att.head_dim, att.feat_dim
    q = att.q(f_in).view(-1, h, d).transpose(0, 1)  # [h, I, d]
    k = att.k(f_side).view(-1, h, d).transpose(0, 1)  # [h, S, d]
    v = f_side.view(-1, h, c // h).transpose(0, 1)  # [h, S, C/h]
    w = torch.softmax(q @ k.transpose(1, 2) / math.sqrt(d), dim=-1)  # [h, I, S]
    return (w @ v).transpose(0, 1).reshape(-1, c)


@torch.no_grad()
def write_back_features(param: Tensor, attended: Tensor, updated: Tensor) -> None:
    """Store the attended rows in the feature parameter (after the optimizer step), so that
    evaluation, export and the next views see them (`AnchorAttentionTerm`'s `write_back`).

    Args:
        param: [A, C] the model's feature parameter; attended: [A, C] the forward's output;
        updated: [I] int64 rows that were replaced (`info['updated']`).
    The Adam moments of those rows are kept: they describe the same feature slot.
    """
    if updated.numel():
        param.index_copy_(0, updated, attended.detach()[updated].to(param.dtype))


class AnchorAttentionTerm(LossTerm):
    """Anchor feature attention in every training view (no loss of its own: value 0).

    Per step from `start_step` on: the in-mask anchors of the view (`masks[index]`) attend to the
    ring's (`ring_frac`, `ring_min_px`, see `ring_width_px`); the render uses the attended features,
    so the photometric gradient reaches the attention's query/key projections, which this term's
    Adam steps in `step_after` (learning rate `lr(step)`), and then the attended rows are written
    into the feature parameter when `write_back`. Empty sets: no override that step (`n_skipped`).
    Needs a model whose render takes `features=` (Scaffold-GS). `coin_cl.gs.refgs.refgs_terms`
    builds it from a `RefGSConfig`.
    """

    name = "attention"

    def __init__(
        self,
        attn: AnchorAttention,
        masks: Sequence[np.ndarray],
        lr: ExpSchedule,
        start_step: float = 0.0,
        ring_frac: float = 0.5,
        ring_min_px: int = 4,
        write_back: bool = True,
    ):
        self.attn = attn
        self.masks = [np.asarray(m, bool) for m in masks]
        self.lr = lr
        self.start_step = float(start_step)
        self.ring_frac, self.ring_min_px, self.write_back = (
            float(ring_frac),
            int(ring_min_px),
            bool(write_back),
        )
        self.weight = 1.0
        self.opt = torch.optim.Adam(self.attn.parameters(), lr=self.lr(0), eps=1e-15)
        self.n_applied = 0
        self.n_skipped = 0
        self._pending: tuple[Tensor, Tensor] | None = None

    def before_render(self, view: View, index: int, step: int, model: Model) -> dict[str, Any]:
        self._pending = None
        if step < self.start_step:
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
            self.ring_frac, self.ring_min_px,
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
        if self.write_back:
            write_back_features(ctx.model.optimizer.params["features"], feats, updated)

    def state_dict(self) -> dict[str, Any]:
        return {"attn": self.attn.state_dict(), "opt": self.opt.state_dict(),
                "n_applied": self.n_applied, "n_skipped": self.n_skipped}  # fmt: skip

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.attn.load_state_dict(sd["attn"])
        self.opt.load_state_dict(sd["opt"])
        self.n_applied = int(sd["n_applied"])
        self.n_skipped = int(sd["n_skipped"])
