"""Plain 3DGS Gaussians (paper 3, the 3DGS parameterisation): the one container that models export,
3DGS PLY files hold, and the renderer's inputs (`coin_cl.engine.Gaussians`) are a view of.

PLY layout (what splat viewers, 3DGS and gsplat read and write), one vertex per Gaussian, all
float32: x y z, nx ny nz (zeros), f_dc_0..2 (SH degree-0 coefficients), f_rest_0..3K-1 (higher SH,
channel-major: all R coefficients, then G, then B), opacity (logit), scale_0..2 (log), rot_0..3
(quaternion wxyz, not necessarily normalised). Written with the SH padded to degree 3 by default
(45 f_rest fields, 62 float32 a record) and Gaussians holding NaN/Inf left out. Other export formats
(.splat, a graphdeco output folder) are `coin_cl.gs.export`'s; point clouds are `coin_cl.scene.ply`'s.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from torch import Tensor

from coin_cl.engine import Gaussians
from coin_cl.gs.sh import MAX_SH_DEGREE, eval_sh, num_sh_bases, rgb_to_sh
from coin_cl.scene.io import atomic_write
from coin_cl.scene.ply import read_ply_vertices

log = logging.getLogger(__name__)

# The vertex properties a 3DGS PLY must have (the rest: f_dc_1.., f_rest_*, normals, are optional).
REQUIRED_PLY_PROPERTIES = ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0")
# The SH degree PLYs are written with by default: graphdeco's SIBR viewer reads a fixed record of
# 62 float32 (degree 3) whatever the header says; name-based readers take any degree.
PLY_SH_DEGREE = MAX_SH_DEGREE


@dataclass
class Splats:
    """N Gaussians in the 3DGS parameterisation (torch float32, any device):

    means [N, 3]; quats [N, 4] wxyz (not necessarily normalised); log_scales [N, 3];
    opacity_logits [N]; sh_dc [N, 3] (degree-0 SH, colour = 0.28209 sh_dc + 0.5);
    sh_rest [N, K, 3] (K = 0, 3, 8 or 15: degrees 1..3).
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    sh_dc: Tensor
    sh_rest: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        want = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
                "sh_dc": (n, 3)}  # fmt: skip
        for name, shape in want.items():
            have = tuple(getattr(self, name).shape)
            if have != shape:
                raise ValueError(f"Splats.{name} has shape {have}, expected {shape}")
        r = self.sh_rest
        if r.ndim != 3 or r.shape[0] != n or r.shape[2] != 3 or r.shape[1] not in (0, 3, 8, 15):
            raise ValueError(f"Splats.sh_rest has shape {tuple(r.shape)}, expected ({n}, 0|3|8|15, 3)")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """The SH degree the coefficients hold (0..3)."""
        return math.isqrt(self.sh_rest.shape[1] + 1) - 1

    def tensors(self) -> list[Tensor]:
        return [getattr(self, f.name) for f in fields(self)]

    def subset(self, keep: Tensor) -> Splats:
        """The Gaussians selected by `keep` ([N] bool or indices)."""
        return Splats(*(t[keep] for t in self.tensors()))

    # ---- the renderer's view ----
    def gaussians(self, cam_center: Tensor | None = None) -> Gaussians:
        """The renderer's inputs: scales exp(log_scales), opacities sigmoid(logits), quats as
        stored, RGB colours [N, 3] of the SH seen from `cam_center` [3] (None: degree 0 only, the
        view-independent colour)."""
        if cam_center is None or self.sh_degree == 0:
            coeffs, degree, dirs = self.sh_dc[:, None], 0, self.means
        else:
            coeffs = torch.cat([self.sh_dc[:, None], self.sh_rest], 1)
            degree, dirs = self.sh_degree, self.means - cam_center
        colors = eval_sh(degree, coeffs, dirs)
        opacities = torch.sigmoid(self.opacity_logits)
        return Gaussians(self.means, self.quats, torch.exp(self.log_scales), opacities, colors)

    @classmethod
    def from_gaussians(cls, g: Gaussians) -> Splats:
        """The inverse of `gaussians()` for RGB colours [N, 3] in [0, 1] (degree 0); opacities
        are clamped to [1e-6, 1 - 1e-6] and scales to >= 1e-12 so the logarithms stay finite."""
        if g.colors.shape[1] != 3:
            raise ValueError(f"Splats hold RGB colours; got {g.colors.shape[1]} channels")
        op = g.opacities.clamp(1e-6, 1 - 1e-6)
        return cls(
            means=g.means,
            quats=g.quats,
            log_scales=torch.log(g.scales.clamp_min(1e-12)),
            opacity_logits=torch.log(op / (1 - op)),
            sh_dc=rgb_to_sh(g.colors),
            sh_rest=torch.zeros(len(g), 0, 3, dtype=g.means.dtype),
        )

    # ---- PLY ----
    def with_sh_degree(self, degree: int) -> Splats:
        """The same Gaussians with `sh_rest` zero-padded (or cut) to SH `degree` (0..3): zero
        higher bands leave every colour as it was; cutting drops the view-dependent part above
        `degree`."""
        k = num_sh_bases(degree) - 1
        r = self.sh_rest
        if r.shape[1] >= k:
            rest = r[:, :k]
        else:
            rest = torch.cat([r, r.new_zeros(r.shape[0], k - r.shape[1], 3)], 1)
        return Splats(self.means, self.quats, self.log_scales, self.opacity_logits, self.sh_dc, rest)

    def finite(self) -> tuple[Splats, int]:
        """(the Gaussians whose every value is finite, how many were dropped)."""
        ok = torch.ones(len(self), dtype=torch.bool, device=self.means.device)
        for t in self.tensors():
            ok &= torch.isfinite(t.reshape(len(self), -1)).all(1)
        dropped = int((~ok).sum())
        return (self if dropped == 0 else self.subset(ok)), dropped

    def finite_for(self, path: str | Path) -> tuple[Splats, int]:
        """`finite()` for a file about to be written: the count logged naming `path`; none left is
        a ValueError naming it."""
        g, dropped = self.finite()
        if dropped:
            if len(g) == 0:
                raise ValueError(f"{path}: all {dropped} Gaussians hold NaN or Inf; nothing to write")
            log.warning("%s: left out %d of %d Gaussians holding NaN or Inf", path, dropped, len(self))
        return g, dropped

    def to_ply(self, path: str | Path, sh_degree: int | None = PLY_SH_DEGREE) -> int:
        """Write the 3DGS PLY layout (module doc; binary little-endian), atomically, with the SH
        padded to `sh_degree` (default 3: the fixed 62-float record graphdeco's SIBR viewer reads;
        None: the degree held). Gaussians holding NaN/Inf are left out (count logged); returns
        that count. All of them non-finite is a ValueError naming `path`."""
        g = self if sh_degree is None else self.with_sh_degree(sh_degree)
        g, dropped = g.finite_for(path)
        n = len(g)
        a = {f.name: getattr(g, f.name).detach().cpu().numpy().astype(np.float32) for f in fields(g)}
        k = a["sh_rest"].shape[1]
        cols: list[tuple[str, np.ndarray]] = []
        cols += [(c, a["means"][:, i]) for i, c in enumerate("xyz")]
        cols += [(c, np.zeros(n, np.float32)) for c in ("nx", "ny", "nz")]
        cols += [(f"f_dc_{i}", a["sh_dc"][:, i]) for i in range(3)]
        # Channel-major, as the 3DGS reference writes features_rest.transpose(1, 2).flatten(1).
        rest_cm = a["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k)
        cols += [(f"f_rest_{i}", rest_cm[:, i]) for i in range(3 * k)]
        cols += [("opacity", a["opacity_logits"])]
        cols += [(f"scale_{i}", a["log_scales"][:, i]) for i in range(3)]
        cols += [(f"rot_{i}", a["quats"][:, i]) for i in range(4)]
        arr = np.empty(n, dtype=[(name, "<f4") for name, _ in cols])
        for name, v in cols:
            arr[name] = v
        el = PlyElement.describe(arr, "vertex")
        atomic_write(path, lambda p: PlyData([el], byte_order="<").write(str(p)))
        return dropped

    @classmethod
    def from_ply(cls, path: str | Path) -> Splats:
        """Read a 3DGS PLY written by coin-cl or by the reference implementation (float32 tensors)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"Gaussian PLY {path} not found")
        v = read_ply_vertices(path, "Gaussian PLY")
        names = v.dtype.names
        missing = [n for n in REQUIRED_PLY_PROPERTIES if n not in names]
        if missing:
            raise ValueError(
                f"{path} is not a 3DGS PLY (missing {missing}); for a point cloud use "
                "coin_cl.scene.ply.read_points_ply"
            )

        def stack(prefix: str) -> np.ndarray:
            cols = sorted((c for c in names if c.startswith(prefix)), key=lambda s: int(s.split("_")[-1]))
            return np.stack([np.asarray(v[c], np.float32) for c in cols], axis=1)

        n = len(v)
        rest = np.zeros((n, 0, 3), np.float32)
        if any(c.startswith("f_rest_") for c in names):
            rest = stack("f_rest_").reshape(n, 3, -1).transpose(0, 2, 1).copy()
        return cls(*(torch.from_numpy(np.ascontiguousarray(x)) for x in (
            np.stack([np.asarray(v[c], np.float32) for c in "xyz"], axis=1), stack("rot_"), stack("scale_"),
            np.asarray(v["opacity"], np.float32), stack("f_dc_"), rest,
        )))  # fmt: skip
