"""Carving the removed object's volume (CoIn's removal, paper 4.2 and supplement C.2).

A 2D-first removal trains the Gaussians of every view on that view's inpaint. Nothing then stops
them from sitting where the object stood: multi-view training places the inpaints' colours on
whatever geometry was there, so novel views see a translucent ghost of the object. Pruning the SfM
points in the masks at the start is not enough: densification and Scaffold-GS's offsets grow them
back. So the region is carved for good:

    the carve volume = { x : in at least `min_fraction` of the training views that see x, x projects
                          inside the (dilated) object mask AND lies more than `margin` in front of
                          that view's background depth D_bg }

D_bg of a view continues the surrounding surfaces into the mask: the sparse SfM points that project
outside the dilated mask, z-buffered on a coarse grid (`cell` px), filled in 2D (Telea) over the
rest of the image. Inside the mask it is an estimate of the background behind the object; where the
true background is further (a hole through), D_bg is nearer and the carve is conservative.

`ScaffoldModel` zeroes the opacity of every neural Gaussian inside the volume at every render (and
leaves them out of its exported PLY), for the whole life of the model: Ref-GS, TE-D and eval.
`background_points` gives points on D_bg inside a view's mask, to seed anchors behind the object.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.background_depth import background_depth, dilate_mask

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CarveConfig:
    """dilate_px: the masks are dilated by this many pixels (the object's rim and mask errors);
    cell: the grid (px) on which sparse depth is z-buffered; margin: carve only what lies more than
    this fraction of D_bg in front of it; min_fraction: share of the views seeing a point that must
    put it in front of the background inside the mask; min_views: and at least this many views;
    scale: D_bg and masks are stored at this fraction of the view size (memory).

    The margin and fraction were measured on the synthetic room (90 and 180-degree arcs, exact
    geometry; tests/test_carve.py): D_bg filled in depth overshoots the true background where a near
    surface (the table under the object) meets a far one (the wall above it) in the mask's ring, so
    a 5 % margin also carved 25-32 % of the true background behind the object; 20 % carves 1.3 % of
    it and 96-98 % of the object's volume. Filling in disparity instead never carved background but
    left 25-40 % of the object."""

    dilate_px: int = 3
    cell: int = 8
    margin: float = 0.2
    min_fraction: float = 0.8
    min_views: int = 2
    scale: float = 0.5

    def __post_init__(self) -> None:
        for name, ok, what in (
            ("dilate_px", isinstance(self.dilate_px, int) and self.dilate_px >= 0, "an integer >= 0"),
            ("cell", isinstance(self.cell, int) and self.cell >= 1, "an integer >= 1"),
            ("margin", 0.0 <= self.margin < 1.0, "in [0, 1)"),
            ("min_fraction", 0.0 < self.min_fraction <= 1.0, "in (0, 1]"),
            ("min_views", isinstance(self.min_views, int) and self.min_views >= 1, "an integer >= 1"),
            ("scale", 0.0 < self.scale <= 1.0, "in (0, 1]"),
        ):
            if not ok:
                raise ValueError(f"CarveConfig.{name} is {getattr(self, name)!r}: give {what}")


class CarveVolume:
    """The carve volume of a scene: per training view its camera, mask and background depth.

    viewmats [V, 4, 4], Ks [V, 3, 3] (at the stored size), sizes [V, 2] (W, H), masks [V, H, W]
    bool, depths [V, H, W] float32 (D_bg, camera z); views of different sizes are padded.
    """

    def __init__(self, viewmats: Tensor, Ks: Tensor, sizes: Tensor, masks: Tensor, depths: Tensor,
                 cfg: CarveConfig) -> None:  # fmt: skip
        self.viewmats, self.Ks, self.sizes = viewmats.float(), Ks.float(), sizes.long()
        self.masks, self.depths, self.cfg = masks.bool(), depths.float(), cfg
        self.lo, self.hi = self._bounds()

    def lookup(self, v: int, points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """World points [N, 3] seen from view `v`: (in frame and in front [N] bool, camera z [N],
        the view's mask [N] bool and D_bg [N] at their pixel; the last two are meaningless where
        not in frame)."""
        pc = points @ self.viewmats[v, :3, :3].T + self.viewmats[v, :3, 3]
        z = pc[:, 2]
        zs = z.clamp_min(1e-6)
        u = pc[:, 0] / zs * self.Ks[v, 0, 0] + self.Ks[v, 0, 2]
        w = pc[:, 1] / zs * self.Ks[v, 1, 1] + self.Ks[v, 1, 2]
        W, H = int(self.sizes[v, 0]), int(self.sizes[v, 1])
        ok = (z > 1e-6) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
        iu, iv = u.clamp(0, W - 1).long(), w.clamp(0, H - 1).long()
        return ok, z, self.masks[v, iv, iu], self.depths[v, iv, iu]

    def unproject(self, v: int, ys: Tensor, xs: Tensor, z: Tensor) -> Tensor:
        """Stored pixels (ys, xs) of view `v` at camera z -> world points [N, 3] (pixel centres)."""
        K, c2w = self.Ks[v], torch.linalg.inv(self.viewmats[v])
        pc = torch.stack([(xs + 0.5 - K[0, 2]) / K[0, 0] * z, (ys + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
        return pc @ c2w[:3, :3].T + c2w[:3, 3]

    def _bounds(self) -> tuple[Tensor, Tensor]:
        """An axis-aligned box around the volume: the mask pixels of the first views unprojected
        between the nearest camera and D_bg; points outside it skip the per-view test."""
        pts = []
        for v in range(len(self.masks)):
            ys, xs = torch.nonzero(self.masks[v], as_tuple=True)
            if len(ys) == 0:
                continue
            d = self.depths[v, ys, xs]
            for t in (0.02, 1.0):  # from near the camera to the background
                pts.append(self.unproject(v, ys, xs, d * t))
        if not pts:
            return torch.zeros(3), torch.zeros(3) - 1  # empty box: nothing is carved
        p = torch.cat(pts)
        return p.amin(0), p.amax(0)

    def __len__(self) -> int:
        return len(self.masks)

    @torch.no_grad()
    def contains(self, points: Tensor) -> Tensor:
        """[N, 3] world points -> [N] bool, inside the carve volume."""
        x = points.detach().float()
        out = torch.zeros(len(x), dtype=torch.bool)
        cand = ((x >= self.lo) & (x <= self.hi)).all(1).nonzero().squeeze(1)
        if len(cand) == 0:
            return out
        xc = x[cand]
        seen = torch.zeros(len(xc), dtype=torch.int32)
        inside = torch.zeros(len(xc), dtype=torch.int32)
        for v in range(len(self.masks)):
            ok, z, m, d = self.lookup(v, xc)
            seen += ok.int()
            inside += (ok & m & (z < d * (1.0 - self.cfg.margin))).int()
        need = torch.maximum(torch.full_like(seen, self.cfg.min_views),
                             torch.ceil(self.cfg.min_fraction * seen.float()).int())  # fmt: skip
        out[cand] = (inside >= need) & (seen > 0)
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"viewmats": self.viewmats, "Ks": self.Ks, "sizes": self.sizes, "masks": self.masks,
                "depths": self.depths, "cfg": self.cfg.__dict__}  # fmt: skip

    @staticmethod
    def from_state(sd: dict[str, Any]) -> CarveVolume:
        return CarveVolume(
            sd["viewmats"], sd["Ks"], sd["sizes"], sd["masks"], sd["depths"], CarveConfig(**sd["cfg"])
        )


def build_carve(cameras: Sequence[Any], masks: Sequence[np.ndarray], points: np.ndarray,
                cfg: CarveConfig | None = None) -> CarveVolume | None:  # fmt: skip
    """The carve volume of the views with a non-empty mask (None when no view has one).

    cameras: `coin_cl.scene.Camera`s; masks: [H, W] bool per camera; points: [N, 3] sparse points."""
    cfg = cfg or CarveConfig()
    views = [(c, np.asarray(m, bool)) for c, m in zip(cameras, masks, strict=True) if np.asarray(m).any()]
    if not views:
        return None
    s = cfg.scale
    Hm = max(max(1, round(c.height * s)) for c, _ in views)
    Wm = max(max(1, round(c.width * s)) for c, _ in views)
    vms, Ks, sizes = [], [], []
    M = torch.zeros(len(views), Hm, Wm, dtype=torch.bool)
    D = torch.zeros(len(views), Hm, Wm)
    for j, (c, m) in enumerate(views):
        d = background_depth(c, m, points, cfg.cell, cfg.dilate_px)
        w, h = max(1, round(c.width * s)), max(1, round(c.height * s))
        grown = dilate_mask(m, cfg.dilate_px).astype(np.uint8)
        M[j, :h, :w] = torch.from_numpy(cv2.resize(grown, (w, h), interpolation=cv2.INTER_NEAREST) > 0)
        D[j, :h, :w] = torch.from_numpy(cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR))
        K = np.asarray(c.K, np.float64).copy()
        K[0] *= w / c.width
        K[1] *= h / c.height
        vms.append(np.asarray(c.viewmat, np.float64))
        Ks.append(K)
        sizes.append((w, h))
    vol = CarveVolume(torch.as_tensor(np.stack(vms)), torch.as_tensor(np.stack(Ks)),
                      torch.as_tensor(sizes), M, D, cfg)  # fmt: skip
    log.info("carve volume from %d views with a mask (D_bg from %d sparse points)", len(vol), len(points))
    return vol


def background_points(vol: CarveVolume, view: int, stride: int = 2) -> np.ndarray:
    """Points on D_bg inside view `view`'s mask (every `stride`-th stored pixel): [P, 3] float32,
    where anchors can grow the background behind the removed object."""
    ys, xs = torch.nonzero(vol.masks[view, ::stride, ::stride], as_tuple=True)
    ys, xs = ys * stride, xs * stride
    return vol.unproject(view, ys, xs, vol.depths[view, ys, xs]).numpy().astype(np.float32)


@torch.no_grad()
def observed_share(vol: CarveVolume, stride: int = 4, tol: float = 0.1) -> tuple[float, list[float]]:
    """How much of the masks other views see (a cheap visibility estimate, before any fit).

    For each view, points on its background depth D_bg inside its mask (every `stride`-th stored
    pixel) are projected into every other view; a point counts as observed when some other view has
    it in frame, outside that view's (dilated) mask and not hidden (its depth at most (1 + tol) x that
    view's D_bg, which outside a mask is the sparse surface the view sees). Returns (the share over
    all sampled mask pixels, the share per view)."""
    per_view, hits, total = [], 0, 0
    for n in range(len(vol)):
        pts = torch.as_tensor(background_points(vol, n, stride))
        if len(pts) == 0:
            per_view.append(0.0)
            continue
        seen = torch.zeros(len(pts), dtype=torch.bool)
        for m in range(len(vol)):
            if m == n:
                continue
            ok, z, mask, d_bg = vol.lookup(m, pts)
            seen |= ok & ~mask & (z <= d_bg * (1.0 + tol))
        per_view.append(float(seen.float().mean()))
        hits += int(seen.sum())
        total += len(pts)
    return (hits / total if total else 0.0), per_view
