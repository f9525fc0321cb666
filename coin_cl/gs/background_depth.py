"""Depth inside the masks continues the surrounding surfaces (CoIn paper 4.2's depth loss
L_D, extended from the reference to every view of a removal).

Each view's mask is trained on that view's inpaint, and a colour says nothing about its distance:
multi-view training then keeps Gaussians where the object stood (they explain every view's fill as
well as a surface behind would), and novel views see a translucent ghost of the object: after the
default run on the shared SPIn-NeRF scene, 54 % of the test masks' pixels render more than 10 % in
front of the true surface.

D_bg of a view (`background_depths`): the nearest background SfM point per z-buffer cell, filled in
2D (Telea) where a cell has none. Background points are those observed outside the object's masks
(`background_point_flags`): the surroundings, and behind the object wherever other views saw past
it; the object's own points are left out. Inside the mask D_bg is therefore what other views
observed there, else the surroundings continued. Read in the SPIn-NeRF test views (against a GS of
those object-absent views) it is more than 10 % in front on 2 % of the mask (from the ring alone,
as the carve volume builds it: 7-10 %), and more than 10 % behind on about a quarter (far points
leaking through sparse cells), hence the weak behind side of the term.

`BackgroundDepthTerm` penalises, on every view with a mask, the rendered expected depth d inside
the (dilated) mask where it leaves a band around D_bg:

    L = mean over mask pixels with alpha > min_alpha of
            relu(1 - margin - d / D_bg)                       (in front: the ghost)
          + behind_weight * relu(d / D_bg - 1 - margin)       (behind: a hole through the surface)

Relative depth, so the term is the same for a room and a valley. The band (`margin`) leaves the
surface its relief; D_bg is coarse (cells of a few pixels, sized by the SfM density, then filled),
so the term asks for the background's surface, not for its details. On the synthetic room with
exact depth (tests/test_gs_background_depth.py) the ghost falls from 0.48 to 0.075 at 300 steps.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.base import Model
from coin_cl.gs.data import View
from coin_cl.gs.terms import LossContext, LossTerm

log = logging.getLogger(__name__)

# Below this many usable mask pixels a view's term is noise; the step goes without it.
MIN_PIXELS = 16
# A background point is observed outside the object's mask in at least this many views (SfM's minimum).
MIN_OUTSIDE_VIEWS = 2
# Inside the mask a z-buffer cell counts with at least this many background points.
MIN_CELL_POINTS = 2
# The automatic cell holds about this many sparse points on average.
CELL_POINTS = 4


def dilate_mask(mask: np.ndarray, px: int) -> np.ndarray:
    """[H, W] bool mask grown by `px` pixels (a square structuring element); px <= 0: a copy."""
    m = np.asarray(mask, bool)
    if px <= 0:
        return m.copy()
    return cv2.dilate(m.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)) > 0


def background_point_flags(cameras: Sequence[Any], masks: Sequence[np.ndarray], points: np.ndarray,
                           dilate_px: int = 3) -> np.ndarray:  # fmt: skip
    """[N] bool: the sparse points that belong to the background, not to the masked object.

    SfM triangulates a point from at least two views that see it, so a background point that some
    views see past the object lies outside the (dilated) object mask in at least two views; a point
    inside no mask cannot be the object either. The rest (inside some mask and outside fewer than
    two) is the object, or background that only views through the object frame, which no view
    observed: both are left out. Views with an empty mask do not vote."""
    from coin_cl.scene.geometry import mask_vote_counts

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    voting = [
        (c, dilate_mask(m, dilate_px)) for c, m in zip(cameras, masks, strict=True) if np.asarray(m).any()
    ]
    if not voting:
        return np.isfinite(pts).all(1)
    seen, inside = mask_vote_counts(pts, [c for c, _ in voting], [m for _, m in voting])
    return np.isfinite(pts).all(1) & ((seen - inside >= MIN_OUTSIDE_VIEWS) | (inside == 0))


def background_depth(cam: Any, mask: np.ndarray, points: np.ndarray, cell: int | None, dilate_px: int,
                     object_free: bool = False, planes: bool = False) -> np.ndarray:  # fmt: skip
    """D_bg of one view [H, W] float32 (camera z): the nearest of the sparse `points` [N, 3] per
    `cell` x `cell` cell, filled in 2D (Telea) over the cells without one. cell=None: from the
    density of the points the view sees (`auto_cell`).

    object_free=False: `points` may hold the object, so only those projecting outside the mask
    dilated by `dilate_px` count, and the mask is filled from its surroundings. object_free=True:
    the caller removed the object's points (`background_point_flags`), so points inside the mask
    count too (background other views observed behind the object); there a cell needs
    `MIN_CELL_POINTS` of them (one SfM outlier must not pull the target forward).
    Raises ValueError when no point lands outside the mask."""
    from coin_cl.gs.depth_prior import inpaint_depth

    H, W = mask.shape
    grown = dilate_mask(mask, dilate_px)
    uv, z = cam.project(points)
    ok = np.isfinite(uv).all(1) & (z > 0)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    iu, iv, zz = uv[ok, 0].astype(int), uv[ok, 1].astype(int), z[ok]
    outside = ~grown[iv, iu]
    if not outside.any():
        raise ValueError(
            f"view {getattr(cam, 'name', '?')}: no sparse point outside its mask; cannot estimate the "
            "background depth behind the object (give more views, or switch the background depth off)"
        )
    if cell is None:
        cell = auto_cell(H, W, int(outside.sum()), int((~grown).sum()))
    if not object_free:
        iu, iv, zz = iu[outside], iv[outside], zz[outside]
    gh, gw = -(-H // cell), -(-W // cell)
    flat = (iv // cell) * gw + iu // cell
    grid = np.full(gh * gw, np.inf)
    np.minimum.at(grid, flat, zz)  # z-buffer: the visible surface per cell
    count = np.bincount(flat, minlength=gh * gw)
    grid, count = grid.reshape(gh, gw), count.reshape(gh, gw)
    cells_in_mask = cv2.resize(grown.astype(np.uint8), (gw, gh), interpolation=cv2.INTER_AREA) > 0
    hole = ~np.isfinite(grid) | (
        cells_in_mask if not object_free else cells_in_mask & (count < MIN_CELL_POINTS)
    )
    filled = inpaint_depth(np.where(hole, np.nan, grid), hole, radius=3)
    depth = cv2.resize(filled, (W, H), interpolation=cv2.INTER_LINEAR)
    if planes:
        from coin_cl.gs.surface_planes import continuation_depth

        fit = np.asarray(points, np.float64)
        if not object_free:  # the object's own points must not make a plane
            px, seen = cam.pixels(fit)
            fit = fit[seen & ~grown[px[:, 1], px[:, 0]]]
        depth = np.minimum(depth, continuation_depth(cam, mask, fit, region=grown))
    return depth.astype(np.float32)


def auto_cell(height: int, width: int, n_points: int, n_pixels: int) -> int:
    """The z-buffer cell (px) at which a cell holds about `CELL_POINTS` of `n_points` spread over
    `n_pixels`, in [2, 16]: finer where SfM is dense (a small image), coarser where it is sparse."""
    if n_points <= 0:
        return 16
    return int(np.clip(round(np.sqrt(CELL_POINTS * max(n_pixels, 1) / n_points)), 2, 16))


def background_depths(cameras: Sequence[Any], masks: Sequence[np.ndarray], points: np.ndarray,
                      cell: int | None = None, dilate_px: int = 3,
                      planes: bool = True) -> list[np.ndarray | None]:  # fmt: skip
    """D_bg [H, W] float32 per view, from the background's sparse points (`background_point_flags`:
    behind the object too, where other views observed it; `planes`: `background_depth`'s); None
    for a view with an empty mask (nothing to hold) or without a sparse point outside its mask
    (logged: that view goes without the term)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    bg_pts = pts[background_point_flags(cameras, masks, pts, dilate_px)]
    log.info(
        "background depth from %d of %d sparse points (the rest are on the object)", len(bg_pts), len(pts)
    )
    out: list[np.ndarray | None] = []
    for cam, m in zip(cameras, masks, strict=True):
        m = np.asarray(m, bool)
        if not m.any():
            out.append(None)
            continue
        try:
            out.append(background_depth(cam, m, bg_pts, cell, dilate_px, object_free=True, planes=planes))
        except ValueError as e:
            log.warning("background depth: %s; this view goes without it", e)
            out.append(None)
    return out


class BackgroundDepthTerm(LossTerm):
    """The background depth term (module doc) on the trainer's views.

    Args:
        depths: D_bg [H, W] per trainer view (None: no term on that view).
        masks: [H, W] bool per trainer view (the object's mask); the term runs on it dilated by
            `dilate_px` (the object's rim is where the ghost's edges show).
        weight: lambda; margin: the band's half width, relative; behind_weight: the weight of the
            behind side (0: one-sided); min_alpha: pixels with rendered alpha at most this are left
            out (their expected depth is ill-defined).
    """

    name = "bg_depth"
    auxiliary = True  # its gradient is capped against the photometric's (coin_cl.gs.balance)

    def __init__(self, depths: Sequence[np.ndarray | None], masks: Sequence[np.ndarray], weight: float = 1.0,
                 margin: float = 0.05, behind_weight: float = 0.5, min_alpha: float = 0.5,
                 dilate_px: int = 2) -> None:  # fmt: skip
        if len(depths) != len(masks):
            raise ValueError(f"{len(depths)} background depths for {len(masks)} masks")
        if not (weight >= 0 and margin >= 0 and behind_weight >= 0):
            raise ValueError(
                f"weight, margin and behind_weight must be >= 0: {weight}, {margin}, {behind_weight}"
            )
        self.weight, self.margin, self.behind_weight = float(weight), float(margin), float(behind_weight)
        self.min_alpha = float(min_alpha)
        self.depths: list[Tensor | None] = []
        self.masks: list[Tensor | None] = []
        for j, (d, m) in enumerate(zip(depths, masks, strict=True)):
            if d is None:
                self.depths.append(None)
                self.masks.append(None)
                continue
            d = np.asarray(d, np.float32)
            if d.shape != np.asarray(m).shape:
                raise ValueError(f"view {j}: background depth {d.shape} and mask {np.shape(m)} differ")
            ok = dilate_mask(m, dilate_px) & np.isfinite(d) & (d > 0)
            self.depths.append(torch.as_tensor(np.where(ok, d, 1.0)))
            self.masks.append(torch.as_tensor(ok))
        self.n_applied = 0

    def active(self, index: int) -> bool:
        return 0 <= index < len(self.depths) and self.depths[index] is not None

    def before_render(self, view: View, index: int, step: int, model: Model) -> dict[str, Any]:
        return {"return_depth": True} if self.active(index) else {}

    def __call__(self, ctx: LossContext) -> Tensor:
        zero = ctx.out.image.new_zeros(())
        if not self.active(ctx.index):
            return zero
        if ctx.out.depth is None:
            raise RuntimeError(
                "background depth term: the render returned no depth (before_render not honoured)"
            )
        D, m = self.depths[ctx.index], self.masks[ctx.index]
        d = ctx.out.depth
        ok = m & (ctx.out.alpha.detach() > self.min_alpha) & torch.isfinite(d)
        n = int(ok.sum())
        if n < MIN_PIXELS:
            return zero
        # Zero the unusable pixels before dividing: `where` then gives them an exact zero gradient.
        r = torch.where(ok, d, D) / D
        front = torch.relu(1.0 - self.margin - r)
        behind = torch.relu(r - 1.0 - self.margin)
        pen = torch.where(ok, front + self.behind_weight * behind, torch.zeros_like(r))
        self.n_applied += 1
        ctx.log["bg_front"] = float((ok & (r < 1.0 - self.margin)).sum()) / n
        return pen.sum() / n

    def state_dict(self) -> dict[str, Any]:
        return {"n_applied": self.n_applied}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.n_applied = int(sd.get("n_applied", 0))
