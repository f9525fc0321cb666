"""EWA projection (kernels/project.cl): 3D Gaussians to screen-space splats, forward and backward."""

from __future__ import annotations

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.ops._util import f32, groups, i32
from coin_cl.engine.runtime import Runtime, resolve_device


def _cam(viewmat: Tensor, K: Tensor) -> Tensor:
    """[16] float32: R row-major, t, fx, fy, cx, cy, the camera as the kernels read it."""
    v = viewmat.detach().to(torch.float32)
    k = K.detach().to(torch.float32)
    return torch.cat([v[:3, :3].reshape(-1), v[:3, 3], torch.stack([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])])


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far, rt):
        n = means.shape[0]
        means2d, conics, depths = rt.empty(n, 2), rt.empty(n, 3), rt.empty(n)
        radii = rt.empty(n, dtype=torch.int32)
        # Kept for the backward, which reads them again without another copy (discrete memory).
        kept = [rt.input(t) for t in (means, quats, scales)] + [rt.array(_cam(viewmat, K))]
        # The outputs stay on the device too: the binning and the rasterizer read them next.
        kept += [rt.array(t, "out", keep=True) for t in (radii, conics)]
        a_m2, a_depths = rt.array(means2d, "out", keep=True), rt.array(depths, "out", keep=True)
        if n:
            rt.run(
                "project.cl", "project_fwd", (groups(n),), (64,),
                [i32(n), *kept[:4], i32(width), i32(height), f32(near), f32(far),
                 a_m2, kept[5], a_depths, kept[4]],
            )  # fmt: skip
        ctx.save_for_backward(*[a.tensor for a in kept[:4]], radii, conics)
        ctx.bufs = [a.buf for a in kept]  # buffers only: a tensor here could make a reference cycle
        ctx.meta = (width, height, near, far, rt, means.dtype)
        ctx.mark_non_differentiable(radii)
        return means2d.to(means.dtype), conics.to(means.dtype), depths.to(means.dtype), radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        means, quats, scales, cam, radii, conics = ctx.saved_tensors
        width, height, near, far, rt, dtype = ctx.meta
        n = means.shape[0]
        outs = [rt.empty(n, 3), rt.empty(n, 4), rt.empty(n, 3)]
        if n:
            grads = [
                rt.input(torch.zeros(shape) if g is None else g)
                for g, shape in ((v_means2d, (n, 2)), (v_conics, (n, 3)), (v_depths, (n,)))
            ]
            a = [rt.reuse(t, b) for t, b in zip(ctx.saved_tensors, ctx.bufs, strict=True)]
            a_outs = [rt.array(t, "out", keep=True) for t in outs]  # the decode's backward may read them
            rt.run(
                "project.cl", "project_bwd", (groups(n),), (64,),
                [i32(n), *a[:4], i32(width), i32(height), f32(near), f32(far), *a[4:], *grads, *a_outs],
            )  # fmt: skip
        v_means, v_quats, v_scales = (o.to(dtype) for o in outs)
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None


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
    device: Runtime | str | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """OpenCL twin of `coin_cl.engine.reference.project` (same arguments and outputs)."""
    rt = resolve_device(device)
    return _Project.apply(means, quats, scales, viewmat, K, int(width), int(height), near, far, rt)
