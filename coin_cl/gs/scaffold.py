"""Scaffold-GS (Lu et al. 2024): anchors with neural features decoded into Gaussians by MLPs.

Each anchor (a voxel centre of the SfM points) holds a 32-d feature, 10 learnable offsets and a
6-d log scale (3 for the offsets, 3 for its Gaussians). Per view, anchors whose Gaussians can
reach the camera frustum are decoded by three 2-layer MLPs from [feature, view direction]:
opacity (tanh; only Gaussians with opacity > 0 are drawn), covariance (3 scales through a
sigmoid times the anchor's scale, 4 quaternion entries) and colour (sigmoid). Anchors grow where
their Gaussians' screen gradients are large (at three voxel levels) and are pruned where their
Gaussians stay transparent; a 0.01 x mean scale-volume term keeps Gaussians from bloating.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from coin_cl.engine import constants as cst
from coin_cl.gs.base import Model, RenderOutput, ndc_grad_norm, splat
from coin_cl.gs.data import Camera
from coin_cl.gs.gaussians import knn_mean_dist
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.sh import rgb_to_sh

PER_ANCHOR = ("anchors", "offsets", "features", "scaling")
MLPS = ("mlp_opacity", "mlp_cov", "mlp_color")
_KEY_BITS = 21  # grid-coordinate hashing: each axis must fit in +-2^20 cells


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
    lambda_scale_reg: float = 0.01  # weight of mean(prod(scales)) over drawn Gaussians
    # anchor growing / pruning (steps are 1-based iteration counts, as in Scaffold-GS)
    start_stat: int = 500
    update_from: int = 1500
    update_interval: int = 100
    update_until: int = 15_000
    grad_threshold: float = 0.0002  # NDC screen-gradient units (see coin_cl.gs.base)
    min_opacity: float = 0.005
    success_threshold: float = 0.8
    update_depth: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    max_anchors: int = 1_000_000  # growth stops here (memory guard)


def scaffold_config_from_dict(d: dict[str, Any]) -> ScaffoldConfig:
    d = dict(d)
    for k in ("lr_offsets", "lr_mlp_opacity", "lr_mlp_cov", "lr_mlp_color"):
        d[k] = ExpSchedule(**d[k])
    return ScaffoldConfig(**d)


def voxelize(points: np.ndarray, voxel: float) -> np.ndarray:
    """[M, 3] centres of the occupied voxels of size `voxel` (sorted, unique)."""
    g = np.unique(np.round(np.asarray(points, np.float64) / voxel), axis=0)
    return (g * voxel).astype(np.float32)


def _grid_keys(coords: Tensor) -> Tensor:
    """[N, 3] int grid coordinates -> [N] int64 unique keys."""
    half = 1 << (_KEY_BITS - 1)
    if coords.numel() and (coords.abs().max() >= half):
        raise ValueError("anchor grid coordinates exceed +-2^20 cells: the voxel size is too small")
    c = coords.long() + half
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


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
        if vs <= 0:
            vs = float(np.median(knn_mean_dist(pts, k=1))) * c.voxel_scale
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
        lrs: dict[str, Any] = {
            "offsets": c.lr_offsets.scaled(self.extent),
            "features": c.lr_features,
            "scaling": c.lr_scaling,
        }
        for mname in MLPS:
            for pname, prm in self.mlps[mname].named_parameters():
                params[f"{mname}.{pname}"] = prm
                lrs[f"{mname}.{pname}"] = getattr(c, f"lr_{mname}")
        self.optimizer = ParamOptimizer(params, lrs)
        self.gen = torch.Generator().manual_seed(seed)
        self._reset_all_stats()

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
        x = self.p["anchors"].detach() @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
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

    def decode(self, cam_center: Tensor, vis: Tensor) -> dict[str, Tensor]:
        """Neural Gaussians of the anchors in `vis` [A] bool, seen from `cam_center` [3].

        Returns means [M,3], quats [M,4], scales [M,3], opacities [M], colors [M,3] for the
        M drawn Gaussians (opacity > 0), plus 'neural_opacity' [V*k] (before the mask) and
        'selected' [V*k] bool (which of the visible anchors' offsets were drawn).
        """
        k = self.cfg.n_offsets
        p = self.p
        anchor = p["anchors"][vis]
        feat = p["features"][vis]
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
    ) -> RenderOutput:
        vis = self.visible_anchors(cam)
        g = self.decode(cam.center, vis)
        image, alpha, depth, meta = splat(
            cam, g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            backend=backend, background=background, return_depth=return_depth, training=training,
            device=self.device,
        )  # fmt: skip
        if g["scales"].shape[0]:
            reg = self.cfg.lambda_scale_reg * g["scales"].prod(dim=1).mean()
        else:
            reg = image.new_zeros(())
        meta.update(
            width=cam.width,
            height=cam.height,
            anchor_visible=vis,
            selected=g["selected"],
            neural_opacity=g["neural_opacity"],
            n_anchors_visible=int(vis.sum()),
        )
        return RenderOutput(image, alpha, depth, reg, meta)

    # ---- statistics and anchor growing ----
    def _reset_all_stats(self) -> None:
        a, k = self.n_anchors, self.cfg.n_offsets
        self.opacity_accum = torch.zeros(a)
        self.anchor_denom = torch.zeros(a)
        self.offset_grad_accum = torch.zeros(a * k)
        self.offset_denom = torch.zeros(a * k)

    def after_backward(self, out: RenderOutput, step: int) -> None:
        """Scaffold-GS `training_statis` (between `start_stat` and `update_until`)."""
        s, c = step + 1, self.cfg
        if not (c.start_stat < s < c.update_until):
            return
        m, k = out.meta, c.n_offsets
        vis = m["anchor_visible"]
        op = m["neural_opacity"].clamp_min(0).view(-1, k)
        self.opacity_accum[vis] += op.sum(1)
        self.anchor_denom[vis] += 1
        # Map drawn Gaussians back to their (anchor, offset) slot.
        slot = torch.zeros(self.n_anchors * k, dtype=torch.bool)
        slot[vis.repeat_interleave(k)] = m["selected"]
        idx = slot.nonzero().squeeze(1)
        drawn = m["radii"] > 0
        g = ndc_grad_norm(m["means2d"], m["width"], m["height"])
        self.offset_grad_accum[idx[drawn]] += g[drawn].to(self.offset_grad_accum.dtype)
        self.offset_denom[idx[drawn]] += 1

    def refine(self, step: int) -> dict[str, int]:
        s, c = step + 1, self.cfg
        if s > c.update_from and s % c.update_interval == 0 and s < c.update_until:
            return self.adjust_anchors()
        return {"grown": 0, "pruned": 0}

    def adjust_anchors(self) -> dict[str, int]:
        """Grow anchors from high-gradient offsets, then prune transparent anchors (Scaffold-GS
        `adjust_anchor`). Returns {'grown': n, 'pruned': n}."""
        c, k = self.cfg, self.cfg.n_offsets
        grads = self.offset_grad_accum / self.offset_denom
        grads = torch.nan_to_num(grads, nan=0.0)
        offset_mask = self.offset_denom > c.update_interval * c.success_threshold * 0.5
        grown = self._grow(grads, offset_mask)
        # Reset statistics of the offsets that were considered; pad for the new anchors.
        self.offset_denom[offset_mask] = 0
        self.offset_grad_accum[offset_mask] = 0
        pad = self.n_anchors * k - self.offset_denom.shape[0]
        self.offset_denom = torch.cat([self.offset_denom, torch.zeros(pad)])
        self.offset_grad_accum = torch.cat([self.offset_grad_accum, torch.zeros(pad)])
        # Prune anchors seen often enough whose Gaussians stayed nearly transparent.
        prune = self.opacity_accum < c.min_opacity * self.anchor_denom
        checked = self.anchor_denom > c.update_interval * c.success_threshold
        prune &= checked
        self.opacity_accum[checked] = 0
        self.anchor_denom[checked] = 0
        n_prune = int(prune.sum())
        if n_prune:
            keep = ~prune
            self.optimizer.keep_rows(list(PER_ANCHOR), keep)
            self.opacity_accum = self.opacity_accum[keep]
            self.anchor_denom = self.anchor_denom[keep]
            kk = keep.repeat_interleave(k)
            self.offset_denom = self.offset_denom[kk]
            self.offset_grad_accum = self.offset_grad_accum[kk]
        return {"grown": grown, "pruned": n_prune}

    def _grow(self, grads: Tensor, offset_mask: Tensor) -> int:
        c, k = self.cfg, self.cfg.n_offsets
        init_len = self.n_anchors * k
        total = 0
        for i in range(c.update_depth):
            if self.n_anchors >= c.max_anchors:
                break
            thr = c.grad_threshold * ((c.update_hierarchy_factor // 2) ** i)
            cand = (grads >= thr) & offset_mask
            cand &= torch.rand(cand.shape, generator=self.gen) > 0.5 ** (i + 1)
            inc = self.n_anchors * k - init_len
            if inc == 0 and i > 0:
                continue  # Scaffold-GS only descends a level after the previous one grew
            cand = torch.cat([cand, torch.zeros(inc, dtype=torch.bool)])
            p = {n: self.p[n].data for n in PER_ANCHOR}
            scaling = torch.exp(p["scaling"])
            all_xyz = p["anchors"][:, None] + p["offsets"] * scaling[:, None, :3]
            size = self.voxel_size * (c.update_init_factor // (c.update_hierarchy_factor**i))
            sel_xyz = all_xyz.reshape(-1, 3)[cand]
            if sel_xyz.shape[0] == 0:
                continue
            sel_keys = _grid_keys(torch.round(sel_xyz / size))
            uniq, inv = torch.unique(sel_keys, return_inverse=True)
            occupied = torch.isin(uniq, _grid_keys(torch.round(p["anchors"] / size)))
            new_keep = ~occupied
            if not bool(new_keep.any()):
                continue
            # Recover the integer cell of each unique key from one of its members.
            first = torch.full((uniq.shape[0],), sel_keys.shape[0], dtype=torch.long)
            first.scatter_reduce_(0, inv, torch.arange(sel_keys.shape[0]), reduce="amin")
            cells = torch.round(sel_xyz[first] / size)
            new_anchor = (cells * size)[new_keep].float()
            feat_rep = p["features"].repeat_interleave(k, 0)[cand]
            feat = torch.full((uniq.shape[0], c.feat_dim), -torch.inf)
            feat = feat.scatter_reduce(
                0, inv[:, None].expand(-1, c.feat_dim), feat_rep, reduce="amax", include_self=False
            )[new_keep]
            budget = c.max_anchors - self.n_anchors
            new_anchor, feat = new_anchor[:budget], feat[:budget]
            n_new = new_anchor.shape[0]
            self.optimizer.append_rows(
                {
                    "anchors": new_anchor,
                    "offsets": torch.zeros(n_new, k, 3),
                    "features": feat,
                    "scaling": torch.full((n_new, 6), float(np.log(size))),
                }
            )
            self.opacity_accum = torch.cat([self.opacity_accum, torch.zeros(n_new)])
            self.anchor_denom = torch.cat([self.anchor_denom, torch.zeros(n_new)])
            total += n_new
        return total

    # ---- export / state ----
    @torch.no_grad()
    def export_gaussians(self, cam_center: Tensor | None = None) -> dict[str, Tensor]:
        """Decode every anchor into plain Gaussians (view-dependent colour frozen at
        `cam_center`, default the origin) in the 3DGS parameterisation (log scales, logits)."""
        center = torch.zeros(3) if cam_center is None else cam_center
        g = self.decode(center, torch.ones(self.n_anchors, dtype=torch.bool))
        op = g["opacities"].clamp(1e-6, 1 - 1e-6)
        return {
            "means": g["means"],
            "quats": g["quats"],
            "scales": torch.log(g["scales"].clamp_min(1e-12)),
            "opacities": torch.log(op / (1 - op)),
            "sh0": rgb_to_sh(g["colors"])[:, None, :],
            "shN": torch.zeros(g["means"].shape[0], 0, 3),
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "extent": self.extent,
            "voxel_size": self.voxel_size,
            "cfg": asdict(self.cfg),
            "optimizer": self.optimizer.state_dict(),
            "stats": {
                "opacity_accum": self.opacity_accum,
                "anchor_denom": self.anchor_denom,
                "offset_grad_accum": self.offset_grad_accum,
                "offset_denom": self.offset_denom,
            },
            "gen": self.gen.get_state(),
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.extent = sd["extent"]
        self.voxel_size = sd["voxel_size"]
        self.optimizer.load_state_dict(sd["optimizer"])
        for k, v in sd["stats"].items():
            setattr(self, k, v.clone())
        self.gen.set_state(sd["gen"])
