"""Per-pixel SSIM with a separable Gaussian window (kernels/ssim.cl), forward and backward: the
structural term of the photometric training loss without torch's convolution temporaries."""

from __future__ import annotations

import torch
from torch import Tensor

from coin_cl.engine.geometry import check_ssim_inputs, gaussian_window
from coin_cl.engine.ops._util import f32, groups, i32
from coin_cl.engine.runtime import Runtime, as_f32, resolve_device

MAX_SSIM_CHANNELS = 16  # each work-item keeps 5 sums per channel in registers


class _SSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, window, sigma, c1, c2, rt):
        B, H, W, C = a.shape
        n = B * H * W
        x, y = as_f32(a), as_f32(b)
        gw = gaussian_window(window, sigma).to(torch.float32)
        defines = {"NUM_CHANNELS": C, "WIN": window}
        out, part = rt.empty(B, H, W), rt.empty(3 * C, B, H, W)  # planar (kernels/ssim.cl)
        if n:
            vstat = rt.scratch(5 * C, n)
            rt.run(
                "ssim.cl", "ssim_fwd_v", (groups(n),), (64,),
                [i32(n), i32(H), i32(W), x, y, gw, vstat], defines=defines, wait=False,
            )  # fmt: skip
            rt.run(
                "ssim.cl", "ssim_fwd_h", (groups(n),), (64,),
                [i32(n), i32(H), i32(W), f32(c1), f32(c2), vstat, gw, (out, "out"), (part, "out")],
                defines=defines,
            )  # fmt: skip
        ctx.save_for_backward(x, y, part, gw)
        ctx.meta = (rt, defines, a.dtype)
        return out.to(a.dtype)

    @staticmethod
    def backward(ctx, v_out):
        x, y, part, gw = ctx.saved_tensors
        rt, defines, dtype = ctx.meta
        B, H, W, C = x.shape
        n = B * H * W
        v_a = rt.empty(B, H, W, C)
        if n:
            hgrad = rt.scratch(3 * C, n)
            rt.run(
                "ssim.cl", "ssim_bwd_h", (groups(n),), (64,),
                [i32(n), i32(H), i32(W), as_f32(v_out), part, gw, hgrad], defines=defines, wait=False,
            )  # fmt: skip
            rt.run(
                "ssim.cl", "ssim_bwd_v", (groups(n),), (64,),
                [i32(n), i32(H), i32(W), x, y, hgrad, gw, (v_a, "out")], defines=defines,
            )  # fmt: skip
        return v_a.to(dtype), None, None, None, None, None, None


def ssim_map(
    a: Tensor,
    b: Tensor,
    window: int = 11,
    sigma: float = 1.5,
    c1: float = 0.01**2,
    c2: float = 0.03**2,
    device: Runtime | str | None = None,
) -> Tensor:
    """OpenCL twin of `coin_cl.engine.reference.ssim_map` (same arguments and output): [B, H, W]
    per-pixel SSIM of a, b [B, H, W, C], averaged over channels. The gradient flows to `a` only (the
    training target `b` is data); b requiring a gradient is an error rather than a silent zero.
    NaN/Inf propagate as in the twin."""
    check_ssim_inputs(a, b)
    if not 1 <= a.shape[-1] <= MAX_SSIM_CHANNELS:
        raise ValueError(f"ssim_map supports 1 to {MAX_SSIM_CHANNELS} channels, got {a.shape[-1]}")
    if 5 * a.shape[-1] * a[..., 0].numel() >= 2**31:
        raise ValueError(f"ssim_map: {tuple(a.shape)} is too large for the kernel's 32-bit indexing; "
                         "split the batch")  # fmt: skip
    if b.requires_grad:
        raise ValueError("ssim_map (OpenCL) differentiates its first image only; detach b")
    rt = resolve_device(device)
    return _SSIM.apply(a, b, int(window), float(sigma), float(c1), float(c2), rt)
