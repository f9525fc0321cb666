"""Scaffold-GS neural-Gaussian decode after the MLPs (kernels/decode.cl), forward and backward."""

from __future__ import annotations

import torch
from torch import Tensor

from coin_cl.engine.ops._util import groups, i32
from coin_cl.engine.runtime import Runtime, as_f32, resolve_device


class _Decode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, anchors, offsets, scaling, opacity, cov, color, vidx, sidx, rt):
        n, k = sidx.shape[0], offsets.shape[1]
        vi, si = vidx.to(torch.int32).contiguous(), sidx.to(torch.int32).contiguous()
        ins = [as_f32(t) for t in (anchors, offsets, scaling, opacity, cov, color)]
        outs = [rt.empty(n, 3), rt.empty(n, 4), rt.empty(n, 3), rt.empty(n), rt.empty(n, 3)]
        if n:
            rt.run(
                "decode.cl", "decode_fwd", (groups(n),), (64,),
                # kept on the device: the projection and the rasterizer read them next
                [i32(n), i32(k), vi, si, *ins, *[rt.array(t, "out", keep=True) for t in outs]],
            )  # fmt: skip
        ctx.save_for_backward(vi, si, ins[1], ins[2], ins[4])
        ctx.meta = (rt, anchors.shape[0], opacity.shape[0], cov.dtype)
        return tuple(o.to(cov.dtype) for o in outs)

    @staticmethod
    def backward(ctx, v_means, v_quats, v_scales, v_opac, v_col):
        vi, si, offsets, scaling, cov = ctx.saved_tensors
        rt, n_anchors, n_off, dtype = ctx.meta
        n, n_vis, k = si.shape[0], vi.shape[0], offsets.shape[1]
        grads = [
            rt.input(torch.zeros(shape) if g is None else g)
            for g, shape in ((v_means, (n, 3)), (v_quats, (n, 4)), (v_scales, (n, 3)), (v_opac, (n,)),
                             (v_col, (n, 3)))
        ]  # fmt: skip
        midx = torch.full((n_off,), -1, dtype=torch.int32)
        midx[si.long()] = torch.arange(n, dtype=torch.int32)
        outs = [rt.empty(n_off), rt.empty(n_off, 7), rt.empty(n_off, 3)]
        # Rows of anchors outside the frustum get no gradient: zeros, which the kernel leaves alone.
        v_offsets, v_scaling = torch.zeros(n_anchors, k, 3), torch.zeros(n_anchors, 6)
        if n_vis:
            rt.run(
                "decode.cl", "decode_bwd", (groups(n_vis),), (64,),
                [i32(n_vis), i32(k), vi, midx, offsets, scaling, cov, *grads,
                 *[(t, "out") for t in outs], (v_offsets, "acc"), (v_scaling, "acc")],
            )  # fmt: skip
        v_o, v_c, v_col_in = (o.to(dtype) for o in outs)
        return None, v_offsets.to(dtype), v_scaling.to(dtype), v_o, v_c, v_col_in, None, None, None


def decode_neural_gaussians(
    anchors: Tensor,
    offsets: Tensor,
    scaling: Tensor,
    opacity: Tensor,
    cov: Tensor,
    color: Tensor,
    vidx: Tensor,
    sidx: Tensor,
    device: Runtime | str | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """OpenCL twin of `coin_cl.engine.reference.decode_neural_gaussians` (same arguments and
    outputs). Gradients flow to offsets, scaling, opacity, cov and color (anchors are fixed)."""
    rt = resolve_device(device)
    return _Decode.apply(anchors, offsets, scaling, opacity, cov, color, vidx, sidx, rt)
