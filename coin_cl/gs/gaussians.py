"""Vanilla 3D Gaussian Splatting.

Parameters (per Gaussian): means [N,3], log-scales [N,3], quaternions [N,4] (wxyz), opacity
logits [N], SH coefficients sh0 [N,1,3] and shN [N,15,3] (degree 3; the active degree grows
by one every `sh_degree_interval` steps up to `sh_degree`).

Densification (gsplat's clone / split / prune / opacity reset) is not the model's business: see
`coin_cl.gs.strategy.DefaultStrategy`, which edits these rows through `model.optimizer`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.gs.base import Model, RenderOutput, inverse_sigmoid, splat
from coin_cl.gs.data import Camera
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.sh import eval_sh, num_sh_bases, rgb_to_sh
from coin_cl.gs.splats import Splats

PER_GAUSSIAN = ("means", "scales", "quats", "opacities", "sh0", "shN")


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
        seed: unused (the initialisation is deterministic); kept for a common constructor.
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
        self.optimizer = ParamOptimizer(params, self.learning_rates())

    def learning_rates(self) -> dict[str, Any]:
        c = self.cfg
        return {
            "means": c.lr_means.scaled(self.extent),
            "scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacities": c.lr_opacities,
            "sh0": c.lr_sh0,
            "shN": c.lr_shN,
        }

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
        colors = eval_sh(deg, coeffs, p["means"] - cam.center_t)
        image, alpha, depth, meta = splat(
            cam, p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]), colors,
            backend=backend, background=background, return_depth=return_depth, training=training,
            device=self.device,
        )  # fmt: skip
        # The activated scales [N, 3] that were drawn, for scale regularisers (loss terms).
        meta.update(width=cam.width, height=cam.height, scales=torch.exp(p["scales"]))
        return RenderOutput(image, alpha, depth, meta)

    # ---- export / state ----
    def export_gaussians(self, cam_center: Tensor | None = None) -> Splats:
        """The parameters themselves (`cam_center` is ignored: SH keeps the view dependence)."""
        p = {k: self.p[k].detach().clone() for k in PER_GAUSSIAN}
        return Splats(p["means"], p["quats"], p["scales"], p["opacities"], p["sh0"][:, 0], p["shN"])

    def state_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "extent": self.extent,
            "cfg": asdict(self.cfg),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.extent = sd["extent"]
        self.optimizer.load_state_dict(sd["optimizer"])


def gaussian_config_from_dict(d: dict[str, Any]) -> GaussianConfig:
    """Rebuild a `GaussianConfig` from `asdict` output (checkpoints); keys it no longer has (the
    densification settings older checkpoints kept here) are ignored."""
    d = {k: v for k, v in d.items() if k in {f.name for f in fields(GaussianConfig)}}
    d["lr_means"] = ExpSchedule(**d["lr_means"])
    return GaussianConfig(**d)
