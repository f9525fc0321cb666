"""Scaffold-GS (Lu et al. 2024): anchors with neural features decoded into Gaussians by MLPs.

Each anchor (a voxel centre of the SfM points) holds a 32-d feature, 10 learnable offsets and a
6-d log scale (3 for the offsets, 3 for its Gaussians). Per view, anchors whose Gaussians can
reach the camera frustum are decoded by three 2-layer MLPs from [feature, view direction]:
opacity (tanh; only Gaussians with opacity > 0 are drawn), covariance (3 scales through a
sigmoid times the anchor's scale, 4 quaternion entries) and colour (sigmoid).

Anchor growing and pruning live in `coin_cl.gs.strategy.ScaffoldStrategy`; the 0.01 x mean
scale-volume regulariser is the loss term `coin_cl.gs.terms.ScaleVolumeReg` (the render exposes
the drawn Gaussians' scales in `meta['scales']`).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, fields
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from coin_cl.engine import Gaussians
from coin_cl.engine import constants as cst
from coin_cl.engine.rendering import decode_neural_gaussians
from coin_cl.gs.base import Model, RenderOutput, splat
from coin_cl.gs.data import Camera
from coin_cl.gs.gaussians import knn_mean_dist
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.splats import Splats

log = logging.getLogger(__name__)

PER_ANCHOR = ("anchors", "offsets", "features", "scaling")
MLPS = ("mlp_opacity", "mlp_cov", "mlp_color")


@dataclass
class ScaffoldConfig:
    """Scaffold-GS defaults (its `arguments/__init__.py`, 30k-step schedule)."""

    feat_dim: int = 32
    n_offsets: int = 10
    voxel_size: float = 0.0  # <= 0: median nearest-neighbour distance of the input points
    voxel_scale: float = 1.0  # multiplies the automatic voxel size (coarser = fewer anchors)
    lr_offsets: ExpSchedule = ExpSchedule(0.01, 0.0001, 30_000)  # x scene extent
    lr_features: float = 0.0075
    lr_scaling: float = 0.007
    lr_mlp_opacity: ExpSchedule = ExpSchedule(0.002, 0.00002, 30_000)
    lr_mlp_cov: ExpSchedule = ExpSchedule(0.004, 0.004, 30_000)
    lr_mlp_color: ExpSchedule = ExpSchedule(0.008, 0.00005, 30_000)


def scaffold_config_from_dict(d: dict[str, Any]) -> ScaffoldConfig:
    """Rebuild a `ScaffoldConfig` from `asdict` output (checkpoints); keys it no longer has (the
    anchor-growing settings and regulariser weight older checkpoints kept here) are ignored."""
    d = {k: v for k, v in d.items() if k in {f.name for f in fields(ScaffoldConfig)}}
    for k in ("lr_offsets", "lr_mlp_opacity", "lr_mlp_cov", "lr_mlp_color"):
        d[k] = ExpSchedule(**d[k])
    return ScaffoldConfig(**d)


# Anchor grid coordinates are hashed with 21 bits per axis (`coin_cl.gs.strategy`), so |x| / voxel
# must stay under 2^20; the voxel keeps GRID_HEADROOM x that margin for anchors grown outward.
GRID_HALF_CELLS = 1 << 20
GRID_HEADROOM = 16


def min_voxel_size(points: np.ndarray) -> float:
    """The smallest voxel size whose anchor grid holds `points` [N, 3] with GRID_HEADROOM x margin
    (a positive float; 1e-12 for an empty or all-zero cloud)."""
    p = np.asarray(points, np.float64)
    reach = float(np.abs(p[np.isfinite(p)]).max()) if p.size and np.isfinite(p).any() else 0.0
    return max(reach * GRID_HEADROOM / GRID_HALF_CELLS, 1e-12)


def voxelize(points: np.ndarray, voxel: float) -> np.ndarray:
    """[M, 3] centres of the occupied voxels of size `voxel` (sorted, unique)."""
    g = np.unique(np.round(np.asarray(points, np.float64) / voxel), axis=0)
    return (g * voxel).astype(np.float32)


class KeptEmpty(Protocol):
    """A volume the model keeps free of Gaussians (`ScaffoldModel.carve`; `coin_cl.gs.carve.CarveVolume`
    is the one the pipeline sets)."""

    def contains(self, points: Tensor) -> Tensor:
        """[N] bool: which of `points` [N, 3] lie inside."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint saves of it."""
        ...


def _mlp(d_in: int, d_hidden: int, d_out: int, act: nn.Module | None) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(d_in, d_hidden), nn.ReLU(), nn.Linear(d_hidden, d_out)]
    if act is not None:
        layers.append(act)
    return nn.Sequential(*layers)


class ScaffoldModel(Model):
    """Scaffold-GS.

    Args:
        points: [N, 3] SfM points (voxelised into anchors). colors: ignored (features start at
            zero, as in Scaffold-GS); accepted for a common constructor.
        extent: scene size (scales the offsets' learning rate).
    """

    kind = "scaffold"

    def __init__(
        self,
        points: np.ndarray,
        colors: np.ndarray | None,
        extent: float,
        cfg: ScaffoldConfig | None = None,
        seed: int = 0,
    ):
        self.cfg = c = cfg or ScaffoldConfig()
        self.extent = float(extent)
        pts = np.asarray(points, dtype=np.float64)
        vs = c.voxel_size
        floor = min_voxel_size(pts)
        if vs <= 0:
            # Unique points: duplicated SfM points (tiny captures) would give a zero median.
            vs = float(np.median(knn_mean_dist(np.unique(pts, axis=0), k=1))) * c.voxel_scale
            if not (np.isfinite(vs) and vs >= floor):
                log.warning("automatic voxel size %.3g is below the anchor grid's floor %.3g "
                            "(|x| / voxel must stay under 2^20 / %d); using the floor",
                            vs, floor, GRID_HEADROOM)  # fmt: skip
                vs = floor
        elif vs < floor:
            raise ValueError(
                f"voxel_size {vs:.3g} is too small for points reaching {np.abs(pts).max():.3g}: the "
                f"anchor grid holds +-2^20 cells (with {GRID_HEADROOM}x headroom); use at least "
                f"{floor:.3g}, or 0 (auto)"
            )
        self.voxel_size = float(vs)
        anchors = torch.as_tensor(voxelize(pts, self.voxel_size))
        a = len(anchors)
        dist = torch.as_tensor(knn_mean_dist(anchors.numpy()), dtype=torch.float32)
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            self.mlps = nn.ModuleDict(
                {
                    "mlp_opacity": _mlp(c.feat_dim + 3, c.feat_dim, c.n_offsets, nn.Tanh()),
                    "mlp_cov": _mlp(c.feat_dim + 3, c.feat_dim, 7 * c.n_offsets, None),
                    "mlp_color": _mlp(c.feat_dim + 3, c.feat_dim, 3 * c.n_offsets, nn.Sigmoid()),
                }
            )
        params: dict[str, Tensor] = {
            "anchors": nn.Parameter(anchors, requires_grad=False),  # fixed (lr 0 in Scaffold-GS)
            "offsets": torch.zeros(a, c.n_offsets, 3),
            "features": torch.zeros(a, c.feat_dim),
            "scaling": torch.log(dist)[:, None].repeat(1, 6),
        }
        for mname in MLPS:
            for pname, prm in self.mlps[mname].named_parameters():
                params[f"{mname}.{pname}"] = prm
        self.optimizer = ParamOptimizer(params, self.learning_rates())
        # A volume kept empty (the pipeline's carve of a removed object, `coin_cl.gs.carve`, sets
        # it): neural Gaussians inside it get zero opacity at every render and are left out of
        # exports, whatever densification grows there. None: nothing is kept empty.
        self.carve: KeptEmpty | None = None

    def learning_rates(self) -> dict[str, Any]:
        c = self.cfg
        lrs: dict[str, Any] = {
            "offsets": c.lr_offsets.scaled(self.extent),
            "features": c.lr_features,
            "scaling": c.lr_scaling,
        }
        for mname in MLPS:
            for pname, _ in self.mlps[mname].named_parameters():
                lrs[f"{mname}.{pname}"] = getattr(c, f"lr_{mname}")
        return lrs

    def _carved(self, g: dict[str, Tensor]) -> dict[str, Tensor]:
        if self.carve is None or g["means"].shape[0] == 0:
            return g
        keep = ~self.carve.contains(g["means"])
        return {**g, "opacities": g["opacities"] * keep.to(g["opacities"].dtype), "kept": keep}

    @property
    def p(self) -> dict[str, nn.Parameter]:
        return self.optimizer.params

    @property
    def n_anchors(self) -> int:
        return int(self.p["anchors"].shape[0])

    @property
    def n_primitives(self) -> int:
        return self.n_anchors * self.cfg.n_offsets

    # ---- visibility and decoding ----
    def anchor_reach(self) -> Tensor:
        """[A] radius around each anchor that bounds its Gaussians' 3-sigma extents."""
        s = torch.exp(self.p["scaling"].detach())
        off = (self.p["offsets"].detach() * s[:, None, :3]).norm(dim=-1).amax(1)
        # Decoded scales are s[3:] * sigmoid(.) < s[3:], so this is a strict bound.
        return off + cst.SIGMA_RADIUS * s[:, 3:].amax(1)

    def visible_anchors(self, cam: Camera) -> Tensor:
        """[A] bool: anchors whose reach sphere intersects the view frustum (sphere-plane test)."""
        V = cam.viewmat_t
        x = self.p["anchors"].detach() @ V[:3, :3].T + V[:3, 3]
        r = self.anchor_reach()
        fx, fy, cx, cy = (float(v) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))
        # Side planes through the optical centre, inward normals, for x/z in [-cx/fx, (W-cx)/fx].
        normals = x.new_tensor(
            [
                [1.0, 0.0, cx / fx],
                [-1.0, 0.0, (cam.width - cx) / fx],
                [0.0, 1.0, cy / fy],
                [0.0, -1.0, (cam.height - cy) / fy],
            ]
        )
        normals = normals / normals.norm(dim=-1, keepdim=True)
        inside = ((x @ normals.T) > -r[:, None]).all(1)
        return inside & (x[:, 2] + r > cst.NEAR_PLANE)

    def decode(
        self, cam_center: Tensor, vis: Tensor, features: Tensor | None = None, backend: str = "opencl"
    ) -> dict[str, Tensor]:
        """Neural Gaussians of the anchors in `vis` [A] bool, seen from `cam_center` [3].

        `features` [A, feat_dim] replaces the feature parameter for this decode (Ref-GS's anchor
        attention renders the current view with attended features; gradients flow through it).

        Returns means [M,3], quats [M,4], scales [M,3], opacities [M], colors [M,3] for the
        M drawn Gaussians (opacity > 0), plus 'neural_opacity' [V*k] (before the mask) and
        'selected' [V*k] bool (which of the visible anchors' offsets were drawn).

        With `self.fused` (default) everything after the MLPs (gathers, activations, quaternion
        normalisation, means) is one op, `coin_cl.engine.decode_neural_gaussians` (an OpenCL
        kernel forward and backward on `backend="opencl"`, its torch twin on "torch"), so no
        per-offset temporaries are built in torch; False is Scaffold-GS' boolean-mask code. Both
        give the same Gaussians (to float rounding) and gradients.
        """
        p = self.p
        if features is None:
            features = p["features"]
        elif tuple(features.shape) != tuple(p["features"].shape):
            raise ValueError(
                f"features override is {tuple(features.shape)}, the model's are {tuple(p['features'].shape)}"
            )
        if not self.fused:
            return self._decode_masked(cam_center, vis, features)
        vidx = vis.nonzero().squeeze(1)  # [V]
        anchor = p["anchors"].index_select(0, vidx)
        ob_view = anchor - cam_center
        ob_view = ob_view / ob_view.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x = torch.cat([features.index_select(0, vidx), ob_view], -1)
        opacity = self.mlps["mlp_opacity"](x).reshape(-1)  # [V*k]
        sel = opacity > 0
        means, quats, scales, opac, colors = decode_neural_gaussians(
            p["anchors"], p["offsets"], p["scaling"], opacity,
            self.mlps["mlp_cov"](x).reshape(-1, 7), self.mlps["mlp_color"](x).reshape(-1, 3),
            vidx, sel.nonzero().squeeze(1), backend=backend, device=self.device,
        )  # fmt: skip
        return {
            "means": means,
            "quats": quats,
            "scales": scales,
            "opacities": opac,
            "colors": colors,
            "neural_opacity": opacity.detach(),
            "selected": sel,
        }

    def _decode_masked(self, cam_center: Tensor, vis: Tensor, features: Tensor) -> dict[str, Tensor]:
        """`decode` as Scaffold-GS writes it (boolean masks, per-offset repeats): the unfused path
        that `benchmarks/train.py --throughput` compares against."""
        k = self.cfg.n_offsets
        p = self.p
        anchor = p["anchors"][vis]
        feat = features[vis]
        scaling = torch.exp(p["scaling"][vis])
        ob_view = anchor - cam_center
        ob_view = ob_view / ob_view.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x = torch.cat([feat, ob_view], -1)
        opacity = self.mlps["mlp_opacity"](x).reshape(-1)
        sel = opacity > 0
        color = self.mlps["mlp_color"](x).reshape(-1, 3)[sel]
        cov = self.mlps["mlp_cov"](x).reshape(-1, 7)[sel]
        scale_rep = scaling.repeat_interleave(k, 0)[sel]
        anchor_rep = anchor.repeat_interleave(k, 0)[sel]
        offsets = p["offsets"][vis].reshape(-1, 3)[sel] * scale_rep[:, :3]
        quats = cov[:, 3:7]
        quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return {
            "means": anchor_rep + offsets,
            "quats": quats,
            "scales": scale_rep[:, 3:] * torch.sigmoid(cov[:, :3]),
            "opacities": opacity[sel],
            "colors": color,
            "neural_opacity": opacity.detach(),
            "selected": sel,
        }

    def render(
        self,
        cam: Camera,
        step: int,
        *,
        backend: str = "opencl",
        background: Tensor | None = None,
        return_depth: bool = False,
        training: bool = False,
        features: Tensor | None = None,
    ) -> RenderOutput:
        """Render `cam`; `features` [A, feat_dim] optionally overrides the anchor features
        (see `decode`)."""
        vis = self.visible_anchors(cam)
        g = self._carved(self.decode(cam.center_t, vis, features, backend=backend))
        image, alpha, depth, meta = splat(
            cam, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            backend=backend, background=background, return_depth=return_depth, training=training,
            device=self.device,
        )  # fmt: skip
        meta.update(
            scales=g["scales"],  # [M, 3] drawn Gaussians' scales, for scale regularisers
            width=cam.width,
            height=cam.height,
            anchor_visible=vis,
            selected=g["selected"],
            neural_opacity=g["neural_opacity"],
            n_anchors_visible=int(vis.sum()),
        )
        return RenderOutput(image, alpha, depth, meta)

    # ---- export / state ----
    @torch.no_grad()
    def export_gaussians(self, cam_center: Tensor | None = None) -> Splats:
        """Decode every anchor into plain Gaussians (view-dependent colour frozen at
        `cam_center`, default the origin) in the 3DGS parameterisation (log scales, logits)."""
        center = torch.zeros(3) if cam_center is None else cam_center
        g = self.decode(center, torch.ones(self.n_anchors, dtype=torch.bool))
        if self.carve is not None:  # carved Gaussians are not part of the model
            keep = ~self.carve.contains(g["means"])
            g = {k: g[k][keep] for k in ("means", "quats", "scales", "opacities", "colors")}
        keys = ("means", "quats", "scales", "opacities", "colors")
        return Splats.from_gaussians(Gaussians(*(g[k] for k in keys)))

    def state_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "extent": self.extent,
            "voxel_size": self.voxel_size,
            "cfg": asdict(self.cfg),
            "optimizer": self.optimizer.state_dict(),
            # restored by `model_kinds.model_from_state`, which knows the volume's class
            **({} if self.carve is None else {"carve": self.carve.state_dict()}),
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.extent = sd["extent"]
        self.voxel_size = sd["voxel_size"]
        self.optimizer.load_state_dict(sd["optimizer"])
        self.carve = None  # a saved volume ("carve") is restored by `model_kinds.model_from_state`
