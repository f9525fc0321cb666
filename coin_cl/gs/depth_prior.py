"""The reference depth loss and its prior (CoIn paper 4.2, Ref-GS; supplement C):
lambda_D * mean |A * R_k + B - D_k| on the reference view with (A, B) a closed-form least-squares
fit; the prior D_k (the dataset's inpainted disparity, or a GS depth inpainted in 2D by
`inpaint_depth`); `ReferenceDepthTerm` plugs the loss into the trainer (`coin_cl.gs.terms`)."""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.gs.base import Model
from coin_cl.gs.data import View
from coin_cl.gs.terms import LossContext, LossTerm
from coin_cl.scene.masks import mask_of_shape

log = logging.getLogger(__name__)

DATASET_DEPTH_PRIOR = "dataset inpainted disparity (LaMa)"
GS_DEPTH_PRIOR = "GS depth of the unmasked scene, inpainted in 2D (cv2.inpaint Telea)"

# Below this many valid (alpha > min_alpha) pixels the affine fit of the depth prior is noise;
# the reference step then goes without the depth term (counted in `n_skipped`).
MIN_DEPTH_PIXELS = 16


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
    m = torch.as_tensor(mask_of_shape(mask, H, W, "reference_depth_loss"), device=render_depth.device)
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
    auxiliary = True  # its gradient is capped against the photometric's (coin_cl.gs.balance)

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
