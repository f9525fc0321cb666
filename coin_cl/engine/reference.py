"""Pure-torch float64 twins of every kernel op, with the same signatures as `coin_cl.engine.ops`.

They follow the kernels' semantics exactly (tile binning by 3-sigma radius, front-to-back
compositing with the alpha clamp, the 1/255 skip and the transmittance stop), written the plainest
way torch allows, so that autograd gives the reference gradients. They are for tests, benchmarks'
error columns and small scenes; they are slow and memory-hungry on large ones.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.errors import PairOverflowError
from coin_cl.engine.geometry import check_ssim_inputs, finite_rows, gaussian_window, quat_to_rotmat


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = cst.NEAR_PLANE,
    far: float = cst.FAR_PLANE,
    device: object = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA projection of 3D Gaussians to screen space (`device` is ignored: the twin runs in torch).

    Args:
        means: [N, 3] world positions. quats: [N, 4] (w, x, y, z). scales: [N, 3] (activated).
        viewmat: [4, 4] world-to-camera (OpenCV axes). K: [3, 3] pinhole intrinsics, pixel
            (x, y) centred at (x + 0.5, y + 0.5).
    Returns:
        means2d [N, 2] pixels, conics [N, 3] (a, b, c) of the inverse 2D covariance,
        depths [N] camera z, radii [N] int32 3-sigma radius in pixels; every output is 0 for a
        culled Gaussian (behind/near/far, non-finite input, zero quaternion, off screen).
    """
    dt = means.dtype
    ok = finite_rows(means, quats, scales) & (quats.norm(dim=-1) > 0)
    # Sanitise before the arithmetic so that culled rows carry no NaN into the graph's gradients.
    safe_q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dt, device=means.device)
    means = torch.where(ok[:, None], means, torch.zeros_like(means))
    quats = torch.where(ok[:, None], quats, safe_q.expand_as(quats))
    scales = torch.where(ok[:, None], scales, torch.zeros_like(scales))

    R, t = viewmat[:3, :3].to(dt), viewmat[:3, 3].to(dt)
    fx, fy, cx, cy = K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item()
    pc = means @ R.T + t
    x, y, z = pc.unbind(-1)
    ok = ok & ((z >= near) & (z <= far))
    z = torch.where(ok, z, torch.ones_like(z))

    Rq = quat_to_rotmat(quats)
    M = Rq * scales[:, None, :]
    cov_c = R @ (M @ M.transpose(1, 2)) @ R.T

    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    u = (x / z).clamp(-(cx / fx + cst.FRUSTUM_MARGIN * tan_fovx),
                      (width - cx) / fx + cst.FRUSTUM_MARGIN * tan_fovx)  # fmt: skip
    v = (y / z).clamp(-(cy / fy + cst.FRUSTUM_MARGIN * tan_fovy),
                      (height - cy) / fy + cst.FRUSTUM_MARGIN * tan_fovy)  # fmt: skip
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * u / z, zero, fy / z, -fy * v / z], dim=-1).reshape(-1, 2, 3)
    cov2d = J @ cov_c @ J.transpose(1, 2)
    a = cov2d[:, 0, 0] + cst.EPS2D
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + cst.EPS2D
    det = a * c - b * b
    ok = ok & (torch.isfinite(det) & (det > 0))
    det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det).clamp_min(cst.EIGEN_FLOOR))
    radius = torch.ceil(cst.SIGMA_RADIUS * torch.sqrt(lam.detach()))
    radius = torch.nan_to_num(radius, nan=0.0, posinf=cst.MAX_RADIUS_PX).clamp(0, cst.MAX_RADIUS_PX)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    md = means2d.detach()
    ok = ok & (radius > 0)
    ok = ok & ((md[:, 0] + radius > 0) & (md[:, 0] - radius < width))
    ok = ok & ((md[:, 1] + radius > 0) & (md[:, 1] - radius < height))

    okf = ok[:, None]
    means2d = torch.where(okf, means2d, torch.zeros_like(means2d))
    conics = torch.where(okf, conics, torch.zeros_like(conics))
    depths = torch.where(ok, z, torch.zeros_like(z))
    radii = torch.where(ok, radius, torch.zeros_like(radius)).to(torch.int32)
    return means2d, conics, depths, radii


def tile_rects(means2d: Tensor, radii: Tensor, tiles_x: int, tiles_y: int) -> Tensor:
    """[N, 4] int64 (x0, y0, x1, y1) half-open tile rectangle each splat is binned to (gsplat's rule)."""
    r = radii.to(means2d.dtype)
    ts = cst.TILE_SIZE
    x0 = torch.floor((means2d[:, 0] - r) / ts).clamp(0, tiles_x)
    x1 = torch.ceil((means2d[:, 0] + r) / ts).clamp(0, tiles_x)
    y0 = torch.floor((means2d[:, 1] - r) / ts).clamp(0, tiles_y)
    y1 = torch.ceil((means2d[:, 1] + r) / ts).clamp(0, tiles_y)
    rect = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
    return torch.where((radii > 0)[:, None], rect, torch.zeros_like(rect))


def rasterize_to_pixels(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    stats: dict | None = None,
    device: object = None,
    bins: object = None,
    defines: dict | None = None,
) -> tuple[Tensor, Tensor]:
    """Front-to-back alpha compositing of projected splats, tile by tile.

    Args:
        means2d [N, 2], conics [N, 3], opacities [N], features [N, C], depths [N] (sort key),
        radii [N] (0 = culled), background [C] or None (zeros).
        max_pairs: cap on (tile, splat) pairs; over it a `PairOverflowError` is raised.
        stats: if given, filled with 'n_pairs'.
        bins: tile lists from `bin_tiles` (either implementation) to composite instead of this
            twin's own 3-sigma binning; the image is the same either way (the opacity-aware
            box only drops pairs that contribute nothing). `device` and `defines` are accepted
            for the kernels' signature and ignored (the twin has the default semantics).
    Returns:
        image [H, W, C] (sum_i w_i f_i + T_final * background), alpha [H, W] (1 - T_final).
    """
    dt = features.dtype
    C = features.shape[1]
    ts = cst.TILE_SIZE
    tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
    bg = torch.zeros(C, dtype=dt) if background is None else background.to(dt)

    if bins is None:
        vis = (radii > 0) & torch.isfinite(opacities) & (opacities > 0)
        order = torch.argsort(depths.detach(), stable=True)
        order = order[vis[order]]
        rect = tile_rects(means2d.detach()[order], radii[order], tiles_x, tiles_y)
        n_pairs = int(((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])).sum())
        if n_pairs > max_pairs:
            raise PairOverflowError(n_pairs, max_pairs)

        def tile_ids(tx: int, ty: int) -> Tensor:
            sel = (rect[:, 0] <= tx) & (tx < rect[:, 2]) & (rect[:, 1] <= ty) & (ty < rect[:, 3])
            return sel.nonzero().squeeze(1)
    else:
        # Tile lists given: index the unsorted arrays through them (already front to back).
        order = torch.arange(means2d.shape[0])
        n_pairs = bins.n_pairs

        def tile_ids(tx: int, ty: int) -> Tensor:
            return bins.tile(ty * tiles_x + tx)

    if stats is not None:
        stats["n_pairs"] = n_pairs
    m2, con, op, feat = means2d[order], conics[order], opacities[order], features[order]

    py, px = torch.meshgrid(torch.arange(ts, dtype=dt), torch.arange(ts, dtype=dt), indexing="ij")
    img = torch.zeros(tiles_y * ts, tiles_x * ts, C, dtype=dt)
    alp = torch.zeros(tiles_y * ts, tiles_x * ts, dtype=dt)
    rows_img, rows_alp = [], []
    for ty in range(tiles_y):
        tiles_img, tiles_alp = [], []
        for tx in range(tiles_x):
            idx = tile_ids(tx, ty)
            gx = (px + tx * ts + 0.5).reshape(-1, 1)
            gy = (py + ty * ts + 0.5).reshape(-1, 1)
            if idx.numel() == 0:
                tiles_img.append(bg.expand(ts * ts, C))
                tiles_alp.append(torch.zeros(ts * ts, dtype=dt))
                continue
            dx = gx - m2[idx, 0]
            dy = gy - m2[idx, 1]
            A, B, Cc = con[idx, 0], con[idx, 1], con[idx, 2]
            sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
            alpha = (op[idx] * torch.exp(-sigma)).clamp(max=cst.MAX_ALPHA)
            keep = (sigma >= 0) & (alpha >= cst.ALPHA_THRESHOLD)
            alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
            incl = torch.cumprod(1 - alpha, dim=1)
            # T is non-increasing, so "stop before T <= T_min" keeps exactly a prefix.
            contrib = incl > cst.TRANSMITTANCE_MIN
            excl = torch.cat([torch.ones_like(incl[:, :1]), incl[:, :-1]], dim=1)
            w = alpha * excl * contrib
            t_final = torch.where(contrib, 1 - alpha, torch.ones_like(alpha)).prod(dim=1)
            tiles_img.append(w @ feat[idx] + t_final[:, None] * bg)
            tiles_alp.append(1 - t_final)
        rows_img.append(torch.stack(tiles_img, 0).reshape(tiles_x, ts, ts, C))
        rows_alp.append(torch.stack(tiles_alp, 0).reshape(tiles_x, ts, ts))
    # [tiles_y, tiles_x, ts, ts, C] -> [tiles_y*ts, tiles_x*ts, C]
    img = torch.stack(rows_img, 0).permute(0, 2, 1, 3, 4).reshape(tiles_y * ts, tiles_x * ts, C)
    alp = torch.stack(rows_alp, 0).permute(0, 2, 1, 3).reshape(tiles_y * ts, tiles_x * ts)
    return img[:height, :width], alp[:height, :width]


def splat_extents(conics: Tensor, opacities: Tensor, radii: Tensor) -> Tensor:
    """[N, 2] half extents (px) of the box outside which o exp(-sigma) < ALPHA_THRESHOLD, padded
    by a pixel (common.h `splat_extent`); -1 where the splat reaches no pixel. Binning caps the
    box by the 3-sigma radius; the rasterizers evaluate every pixel of the uncapped box inside a
    tile the splat is binned to."""
    o = opacities
    a, b, c = conics.unbind(-1)
    det = a * c - b * b
    ok = (radii > 0) & torch.isfinite(o) & (o >= cst.ALPHA_THRESHOLD) & (det > 0)
    det = torch.where(ok, det, torch.ones_like(det))
    t = torch.log(torch.where(ok, o, torch.ones_like(o)) / cst.ALPHA_THRESHOLD).clamp_min(0)
    ex = (torch.sqrt(2 * t * c / det) + 1).clamp(max=cst.MAX_RADIUS_PX)
    ey = (torch.sqrt(2 * t * a / det) + 1).clamp(max=cst.MAX_RADIUS_PX)
    return torch.where(ok[:, None], torch.stack([ex, ey], -1), torch.full_like(conics[:, :2], -1.0))


def bin_tiles(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    device: object = None,
):
    """Twin of `coin_cl.engine.ops.bin_tiles`: the same `TileBins`, built the plainest way (a
    Python loop over tiles), for tests on small scenes."""
    from coin_cl.engine.ops.bin import TileBins  # a dataclass only: no kernel is touched

    ts = cst.TILE_SIZE
    tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
    ext = splat_extents(conics.detach().double(), opacities.detach().double(), radii)
    m = means2d.detach().double()
    capped = torch.minimum(ext, radii.double()[:, None])
    x0 = torch.floor((m[:, 0] - capped[:, 0]) / ts).clamp(0, tiles_x)
    y0 = torch.floor((m[:, 1] - capped[:, 1]) / ts).clamp(0, tiles_y)
    x1 = torch.ceil((m[:, 0] + capped[:, 0]) / ts).clamp(0, tiles_x)
    y1 = torch.ceil((m[:, 1] + capped[:, 1]) / ts).clamp(0, tiles_y)
    rect = torch.stack([x0, y0, x1, y1], -1).long()
    empty = (ext[:, 0] < 0) | (rect[:, 2] <= rect[:, 0]) | (rect[:, 3] <= rect[:, 1])
    rect[empty] = 0
    area = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])
    n_pairs = int(area.sum())
    if n_pairs > max_pairs:
        raise PairOverflowError(n_pairs, max_pairs)
    order = torch.argsort(depths.detach(), stable=True)
    order = order[area[order] > 0]
    starts, lists = [], []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            r = rect[order]
            sel = (r[:, 0] <= tx) & (tx < r[:, 2]) & (r[:, 1] <= ty) & (ty < r[:, 3])
            starts.append(sum(len(x) for x in lists))
            lists.append(order[sel])
    ids = torch.cat(lists) if lists else torch.zeros(0, dtype=torch.int64)
    tile_start = torch.tensor(starts, dtype=torch.int32)
    tile_end = torch.cat([tile_start[1:], torch.tensor([ids.numel()], dtype=torch.int32)])
    pair_start = torch.zeros(means2d.shape[0] + 1, dtype=torch.int32)
    pair_start[1:] = torch.cumsum(area, 0)
    # Splat g's slots, in its tiles' row-major order (the order the fixed reduction sums in).
    slots = [[] for _ in range(means2d.shape[0])]
    for j, g in enumerate(ids.tolist()):
        slots[g].append(j)
    pair_slot = torch.tensor([j for s in slots for j in s], dtype=torch.int32)
    return TileBins(
        tiles_x, tiles_y, tile_start, tile_end, ids.to(torch.int32), pair_start, pair_slot,
        ext.float(), n_pairs=n_pairs, n_visible=int(order.numel()),
    )  # fmt: skip


def decode_neural_gaussians(
    anchors: Tensor,
    offsets: Tensor,
    scaling: Tensor,
    opacity: Tensor,
    cov: Tensor,
    color: Tensor,
    vidx: Tensor,
    sidx: Tensor,
    device: object = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Scaffold-GS' neural Gaussians from its MLP outputs (`device` is ignored).

    Args:
        anchors [A, 3], offsets [A, k, 3], scaling [A, 6] (log: offset scale, Gaussian scale): the
            anchor parameters. opacity [V*k] (tanh output), cov [V*k, 7] (3 scale logits, 4
            quaternion entries), color [V*k, 3] (sigmoid output): the MLPs' outputs for the V
            visible anchors vidx [V] (int, unique). sidx [M] (int): the drawn offsets, indices
            into V*k (Scaffold-GS draws those with opacity > 0).
    Returns:
        means [M, 3] = anchor + offset * exp(scaling[:3]), quats [M, 4] (normalised, the norm
        clamped at 1e-12), scales [M, 3] = exp(scaling[3:]) * sigmoid(cov[:3]), opacities [M],
        colors [M, 3].
    """
    k = offsets.shape[1]
    sidx = sidx.long()
    a = vidx.long()[torch.div(sidx, k, rounding_mode="floor")]
    j = sidx % k
    s = torch.exp(scaling[a])
    cs, r = cov[sidx].split((3, 4), dim=1)
    return (
        anchors[a] + offsets[a, j] * s[:, :3],
        r / r.norm(dim=-1, keepdim=True).clamp_min(1e-12),
        s[:, 3:] * torch.sigmoid(cs),
        opacity[sidx],
        color[sidx],
    )


def ssim_map(
    a: Tensor,
    b: Tensor,
    window: int = 11,
    sigma: float = 1.5,
    c1: float = 0.01**2,
    c2: float = 0.03**2,
    device: object = None,
) -> Tensor:
    """Per-pixel SSIM (separable Gaussian window, zero padding as in 3DGS' training loss).

    Args:
        a, b: [B, H, W, C] images (any C). window: odd width, sigma: the Gaussian's, c1, c2: the
            stabilising constants (> 0 keeps flat windows finite: SSIM 1 where a = b). `device` is
            ignored (the twin's signature is the op's).
    Returns:
        [B, H, W] SSIM averaged over channels, in a's dtype; differentiable in both images. A NaN/Inf
        pixel makes the SSIM of every window it touches NaN (the training loss turns non-finite and
        the trainer stops with `NonFiniteError`, naming the step).
    """
    check_ssim_inputs(a, b)
    g = gaussian_window(window, sigma).to(a.dtype)
    pad = window // 2
    x = F.pad(a.permute(0, 3, 1, 2), (pad, pad, pad, pad))
    y = F.pad(b.to(a.dtype).permute(0, 3, 1, 2), (pad, pad, pad, pad))
    c = x.shape[1]
    stats = torch.cat([x, y, x * x, y * y, x * y], 1)
    k = g.numel()
    stats = F.conv2d(stats, g.view(1, 1, 1, k).expand(5 * c, 1, 1, k), groups=5 * c)
    stats = F.conv2d(stats, g.view(1, 1, k, 1).expand(5 * c, 1, k, 1), groups=5 * c)
    mu_x, mu_y, sxx, syy, sxy = stats.split(c, 1)
    mu_xy = mu_x * mu_y
    mu_xx, mu_yy = mu_x * mu_x, mu_y * mu_y
    num = (2 * mu_xy + c1) * (2 * (sxy - mu_xy) + c2)
    den = (mu_xx + mu_yy + c1) * ((sxx - mu_xx) + (syy - mu_yy) + c2)
    return (num / den).mean(1)
