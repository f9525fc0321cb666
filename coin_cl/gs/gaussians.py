"""Vanilla 3D Gaussian Splatting with gsplat-style default densification.

Parameters (per Gaussian): means [N,3], log-scales [N,3], quaternions [N,4] (wxyz), opacity
logits [N], SH coefficients sh0 [N,1,3] and shN [N,15,3] (degree 3; the active degree grows
by one every `sh_degree_interval` steps up to `sh_degree`).

Densification follows gsplat's `DefaultStrategy`: every `refine_every` steps between
`refine_start` and `refine_stop`, Gaussians whose mean NDC screen gradient exceeds `grow_grad2d`
are cloned (if small in 3D) or split into two (if large); low-opacity and (after the first
opacity reset) very large Gaussians are pruned; every `reset_every` steps opacities are clamped
to twice the prune threshold.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.engine.geometry import quat_to_rotmat
from coin_cl.gs.base import Model, RenderOutput, inverse_sigmoid, ndc_grad_norm, splat
from coin_cl.gs.data import Camera
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.sh import eval_sh, num_sh_bases, rgb_to_sh

PER_GAUSSIAN = ("means", "scales", "quats", "opacities", "sh0", "shN")


@dataclass
class DensifyConfig:
    """gsplat DefaultStrategy defaults. Screen gradient in NDC units (see `coin_cl.gs.base`),
    which is the pixel-position gradient times half the image size; screen sizes in pixels."""

    prune_opa: float = 0.005  # prune when opacity falls below
    grow_grad2d: float = 0.0002  # mean NDC screen-gradient norm to grow (clone or split)
    grow_scale3d: float = 0.01  # x scene extent: at most this large => clone, else split
    prune_scale3d: float = 0.1  # x scene extent: larger => prune (after the first reset)
    prune_radius_px: float = 0.0  # > 0: also prune splats whose 3-sigma radius exceeded this (px)
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    split_factor: float = 1.6  # children of a split get scale / 1.6 (3DGS)
    max_gaussians: int = 3_000_000  # growth stops here (memory guard)


@dataclass
class GaussianConfig:
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    init_opacity: float = 0.1
    init_scale: float = 1.0  # x mean distance to the 3 nearest points
    lr_means: ExpSchedule = ExpSchedule(1.6e-4, 1.6e-6, 30_000)  # x scene extent
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    densify: DensifyConfig = field(default_factory=DensifyConfig)


def knn_mean_dist(points: np.ndarray, k: int = 3) -> np.ndarray:
    """[N] mean distance from each point to its k nearest neighbours (floored at 1e-7)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= 1:
        return np.full(len(pts), 1e-2)
    kk = min(k + 1, len(pts))
    d, _ = cKDTree(pts).query(pts, k=kk)
    return np.maximum(d[:, 1:].mean(1), 1e-7)


class GaussianModel(Model):
    """Vanilla 3DGS.

    Args:
        points: [N, 3] initial means; colors: [N, 3] in [0, 1] or None (grey).
        extent: scene size used to scale the means' learning rate and the 3D size thresholds.
    """

    kind = "3dgs"

    def __init__(
        self,
        points: np.ndarray,
        colors: np.ndarray | None,
        extent: float,
        cfg: GaussianConfig | None = None,
        seed: int = 0,
    ):
        self.cfg = cfg or GaussianConfig()
        self.extent = float(extent)
        pts = torch.as_tensor(np.asarray(points), dtype=torch.float32)
        n = len(pts)
        col = (
            torch.full((n, 3), 0.5)
            if colors is None
            else torch.as_tensor(np.asarray(colors), dtype=torch.float32)
        )
        dist = torch.as_tensor(knn_mean_dist(points), dtype=torch.float32)
        k = num_sh_bases(self.cfg.sh_degree)
        params = {
            "means": pts.clone(),
            "scales": torch.log(dist * self.cfg.init_scale)[:, None].repeat(1, 3),
            "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
            "opacities": torch.full((n,), float(inverse_sigmoid(self.cfg.init_opacity))),
            "sh0": rgb_to_sh(col)[:, None, :],
            "shN": torch.zeros(n, k - 1, 3),
        }
        c = self.cfg
        lrs = {
            "means": c.lr_means.scaled(self.extent),
            "scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacities": c.lr_opacities,
            "sh0": c.lr_sh0,
            "shN": c.lr_shN,
        }
        self.optimizer = ParamOptimizer(params, lrs)
        self.gen = torch.Generator().manual_seed(seed)
        self._reset_stats()

    # ---- accessors ----
    @property
    def p(self) -> dict[str, torch.nn.Parameter]:
        return self.optimizer.params

    @property
    def n_primitives(self) -> int:
        return int(self.p["means"].shape[0])

    def sh_degree_at(self, step: int) -> int:
        return min(step // max(self.cfg.sh_degree_interval, 1), self.cfg.sh_degree)

    # ---- rendering ----
    def render(
        self,
        cam: Camera,
        step: int,
        *,
        backend: str = "opencl",
        background: Tensor | None = None,
        return_depth: bool = False,
        training: bool = False,
    ) -> RenderOutput:
        p = self.p
        deg = self.sh_degree_at(step)
        coeffs = torch.cat([p["sh0"], p["shN"][:, : num_sh_bases(deg) - 1]], 1)
        colors = eval_sh(deg, coeffs, p["means"] - cam.center)
        image, alpha, depth, meta = splat(
            cam, p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]), colors,
            backend=backend, background=background, return_depth=return_depth, training=training,
            device=self.device,
        )  # fmt: skip
        meta["width"], meta["height"] = cam.width, cam.height
        return RenderOutput(image, alpha, depth, image.new_zeros(()), meta)

    # ---- densification ----
    def _reset_stats(self) -> None:
        n = self.n_primitives
        self.grad2d = torch.zeros(n)
        self.count = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    def after_backward(self, out: RenderOutput, step: int) -> None:
        if step >= self.cfg.densify.refine_stop:
            return
        m = out.meta
        vis = m["radii"] > 0
        g = ndc_grad_norm(m["means2d"], m["width"], m["height"])
        self.grad2d[vis] += g[vis].to(self.grad2d.dtype)
        self.count[vis] += 1
        self.max_radii[vis] = torch.maximum(self.max_radii[vis], m["radii"][vis].float())

    def refine(self, step: int) -> dict[str, int]:
        """gsplat DefaultStrategy.step_post_backward for `step` (counted from 0)."""
        d = self.cfg.densify
        # s counts completed iterations, so "every 100" means after the 100th, 200th, ... step.
        s = step + 1
        out = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if s >= d.refine_stop:
            return out
        if s > d.refine_start and s % d.refine_every == 0:
            out["cloned"], out["split"] = self._grow(s)
            out["pruned"] = self._prune(s)
            self._reset_stats()
        if s % d.reset_every == 0:
            self._reset_opacity()
            out["reset"] = 1
        return out

    def _grow(self, s: int) -> tuple[int, int]:
        d = self.cfg.densify
        if self.n_primitives >= d.max_gaussians:
            return 0, 0
        grads = self.grad2d / self.count.clamp_min(1)
        high = grads > d.grow_grad2d
        small = torch.exp(self.p["scales"].data).amax(-1) <= d.grow_scale3d * self.extent
        dup = high & small
        split = high & ~small
        n_dup, n_split = int(dup.sum()), int(split.sum())
        if n_dup:
            self.optimizer.append_rows({k: self.p[k].data[dup] for k in PER_GAUSSIAN})
            self._pad_stats(n_dup, dup)
            split = torch.cat([split, split.new_zeros(n_dup)])
        if n_split:
            self._split(split)
        return n_dup, n_split

    def _pad_stats(self, n: int, src: Tensor) -> None:
        self.grad2d = torch.cat([self.grad2d, self.grad2d[src]])
        self.count = torch.cat([self.count, self.count[src]])
        self.max_radii = torch.cat([self.max_radii, self.max_radii[src]])

    def _split(self, mask: Tensor) -> None:
        """Replace each selected Gaussian with two, sampled from it, scales / split_factor."""
        p = {k: self.p[k].data for k in PER_GAUSSIAN}
        scales = torch.exp(p["scales"][mask])
        R = quat_to_rotmat(p["quats"][mask])
        noise = torch.randn(2, *scales.shape, generator=self.gen)
        offs = torch.einsum("nij,bnj->bni", R, scales[None] * noise)
        new = {
            "means": (p["means"][mask][None] + offs).reshape(-1, 3),
            "scales": torch.log(scales / self.cfg.densify.split_factor).repeat(2, 1),
        }
        for k in ("quats", "opacities", "sh0", "shN"):
            v = p[k][mask]
            new[k] = v.repeat(2, *([1] * (v.dim() - 1)))
        keep = ~mask
        self.optimizer.keep_rows(list(PER_GAUSSIAN), keep)
        self.optimizer.append_rows(new)
        n_new = int(new["means"].shape[0])
        for name in ("grad2d", "count", "max_radii"):
            v = getattr(self, name)[keep]
            setattr(self, name, torch.cat([v, v.new_zeros(n_new)]))

    def _prune(self, s: int) -> int:
        d = self.cfg.densify
        prune = torch.sigmoid(self.p["opacities"].data) < d.prune_opa
        if s > d.reset_every:
            prune |= torch.exp(self.p["scales"].data).amax(-1) > d.prune_scale3d * self.extent
            if d.prune_radius_px > 0:
                prune |= self.max_radii > d.prune_radius_px
        n = int(prune.sum())
        if n:
            keep = ~prune
            self.optimizer.keep_rows(list(PER_GAUSSIAN), keep)
            for name in ("grad2d", "count", "max_radii"):
                setattr(self, name, getattr(self, name)[keep])
        return n

    def _reset_opacity(self) -> None:
        cap = float(inverse_sigmoid(self.cfg.densify.prune_opa * 2.0))
        self.optimizer.set_rows("opacities", self.p["opacities"].data.clamp_max(cap))

    # ---- export / state ----
    def export_gaussians(self) -> dict[str, Tensor]:
        return {k: self.p[k].detach().clone() for k in PER_GAUSSIAN}

    def state_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "extent": self.extent,
            "cfg": asdict(self.cfg),
            "optimizer": self.optimizer.state_dict(),
            "stats": {"grad2d": self.grad2d, "count": self.count, "max_radii": self.max_radii},
            "gen": self.gen.get_state(),
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.extent = sd["extent"]
        self.optimizer.load_state_dict(sd["optimizer"])
        for k, v in sd["stats"].items():
            setattr(self, k, v.clone())
        self.gen.set_state(sd["gen"])


def gaussian_config_from_dict(d: dict[str, Any]) -> GaussianConfig:
    """Rebuild a `GaussianConfig` from `asdict` output (checkpoints)."""
    d = dict(d)
    d["densify"] = DensifyConfig(**d["densify"])
    d["lr_means"] = ExpSchedule(**d["lr_means"])
    return GaussianConfig(**d)
