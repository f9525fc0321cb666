"""Float64 torch twin of `coin_cl.engine.ops.warp.warp_features`: same signature, same semantics, written the
plainest way torch allows so that autograd gives the reference gradient (tests, benchmarks' error
columns, small scenes). See `coin_cl.engine.ops.warp` for the semantics."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.warp_spec import STATUS, _as_tensor, camera_vector, check_inputs


def _project(P: Tensor, K: Tensor, V: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(u, v, z, ok): ok where z > 0 and everything is finite (as kernels/warp.cl cam_project)."""
    pc = P @ V[:3, :3].T + V[:3, 3]
    x, y, z = pc.unbind(1)
    with torch.no_grad():
        ok = (z > 0) & torch.isfinite(pc).all(1)
    zs = torch.where(ok, z, torch.ones_like(z))
    u = K[0, 0] * (x / zs) + K[0, 2]
    v = K[1, 1] * (y / zs) + K[1, 2]
    ok = ok & torch.isfinite(u) & torch.isfinite(v)
    return u, v, z, ok


def _inside(u: Tensor, v: Tensor, w: int, h: int) -> Tensor:
    return (u >= 0) & (u < w) & (v >= 0) & (v < h)


def warp_features(
    points: Tensor,
    src_K,
    src_viewmat,
    src_features: Tensor,
    dst_K,
    dst_viewmat,
    dst_width: int,
    dst_height: int,
    src_depth: Tensor | None = None,
    depth_tol: float = cst.WARP_DEPTH_TOL,
    src_depth_tol: float = cst.WARP_SRC_DEPTH_TOL,
    footprint: str = "bilinear",
    stats: dict[str, Any] | None = None,
    device: object = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Twin of `coin_cl.engine.ops.warp.warp_features` (same arguments and outputs; `device` is ignored)."""
    W2, H2 = int(dst_width), int(dst_height)
    check_inputs(points, src_features, W2, H2, src_depth, depth_tol, src_depth_tol, footprint)
    camera_vector(src_K, src_viewmat, "source camera")  # the op's checks (finite, shapes, focal > 0)
    camera_vector(dst_K, dst_viewmat, "target camera")
    sK, sV = (
        _as_tensor(src_K, "source camera K", (3, 3)),
        _as_tensor(src_viewmat, "source camera viewmat", (4, 4)),
    )
    dK, dV = (
        _as_tensor(dst_K, "target camera K", (3, 3)),
        _as_tensor(dst_viewmat, "target camera viewmat", (4, 4)),
    )
    F = src_features.to(torch.float64)
    H, W, C = F.shape
    m = points.shape[0]
    P = points.detach().to(torch.float64)
    finite = torch.isfinite(P).all(1)
    P = torch.where(finite[:, None], P, torch.zeros_like(P))
    su, sv, sz, s_ok = _project(P, sK, sV)
    du, dv, dz, d_ok = _project(P, dK, dV)
    s_in = _inside(su, sv, W, H)
    occluded = torch.zeros(m, dtype=torch.bool)
    if src_depth is not None:
        D = src_depth.detach().to(torch.float64)
        qx = su.nan_to_num(0).clamp(0, W - 1).floor().long()
        qy = sv.nan_to_num(0).clamp(0, H - 1).floor().long()
        d = D[qy, qx]
        occluded = torch.isfinite(d) & (d > 0) & (sz > d * (1 + src_depth_tol))
    d_in = _inside(du, dv, W2, H2)
    status = torch.zeros(m, dtype=torch.int64)
    # first failure wins: assign in reverse order of the checks
    status[~d_in] = 6
    status[~d_ok] = 5
    status[occluded] = 4
    status[~s_in] = 3
    status[~s_ok] = 2
    status[~finite] = 1
    valid = status == 0
    idx = valid.nonzero().squeeze(1)
    su, sv, du, dv, dz = su[idx], sv[idx], du[idx], dv[idx], dz[idx]

    # bilinear gather, corners clamped to the image
    x, y = su - 0.5, sv - 0.5
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    ix = [(x0 + k).long().clamp(0, W - 1) for k in (0, 1)]
    iy = [(y0 + k).long().clamp(0, H - 1) for k in (0, 1)]
    feats = (
        ((1 - fx) * (1 - fy))[:, None] * F[iy[0], ix[0]]
        + (fx * (1 - fy))[:, None] * F[iy[0], ix[1]]
        + ((1 - fx) * fy)[:, None] * F[iy[1], ix[0]]
        + (fx * fy)[:, None] * F[iy[1], ix[1]]
    )

    # target footprint taps: (point, pixel, weight)
    if footprint == "bilinear":
        x, y = du - 0.5, dv - 0.5
        x0, y0 = x.floor(), y.floor()
        fx, fy = x - x0, y - y0
        taps = []
        for kx, ky in ((0, 0), (1, 0), (0, 1), (1, 1)):
            qx, qy = (x0 + kx).long(), (y0 + ky).long()
            w = (fx if kx else 1 - fx) * (fy if ky else 1 - fy)
            taps.append((qx, qy, w))
    else:
        taps = [(du.floor().long(), dv.floor().long(), torch.ones_like(du))]
    n = idx.numel()
    pt = torch.cat([torch.arange(n)] * len(taps))
    qx = torch.cat([t[0] for t in taps])
    qy = torch.cat([t[1] for t in taps])
    w = torch.cat([t[2] for t in taps])
    keep = (w > 0) & (qx >= 0) & (qx < W2) & (qy >= 0) & (qy < H2)
    pt, qx, qy, w = pt[keep], qx[keep], qy[keep], w[keep]
    pix = qy * W2 + qx
    z = dz[pt]
    zmin = torch.full((H2 * W2,), float("inf"), dtype=torch.float64).scatter_reduce(0, pix, z, "amin")
    win = z <= zmin[pix] * (1 + depth_tol)
    pt, pix, w = pt[win], pix[win], w[win]
    wsum = torch.zeros(H2 * W2, dtype=torch.float64).index_add(0, pix, w)
    acc = torch.zeros(H2 * W2, C, dtype=torch.float64).index_add(0, pix, w[:, None] * feats[pt])
    has = wsum > 0
    out = acc / torch.where(has, wsum, torch.ones_like(wsum))[:, None]
    depth = torch.where(has, zmin, torch.zeros_like(zmin))
    if stats is not None:
        counts = torch.bincount(status, minlength=len(STATUS))
        stats.update({f"n_{s}": int(c) for s, c in zip(STATUS, counts.tolist())})
        stats.update(n_points=m, status=status.to(torch.int32))
    dtype = src_features.dtype
    return out.view(H2, W2, C).to(dtype), wsum.view(H2, W2).to(dtype), depth.view(H2, W2).to(dtype)
