"""Device limits (coin_cl.engine.limits): a device whose work-group size, kernel work-group size or
local memory is below what the 256-wide GPU rasterizer needs gets a narrower variant that still
matches the float64 twin; a limit no variant fits, or a buffer over the largest allocation, is a
clear error naming the device and the limit. Low limits are simulated on the CPU device."""

import dataclasses

import pytest
import torch
from conftest import small_mode

from coin_cl.engine import ops, reference, runtime
from coin_cl.engine.errors import DeviceLimitError
from coin_cl.engine.limits import RASTER_GPU_GROUPS, query_limits, raster_gpu_local_bytes
from coin_cl.engine.runtime import Runtime, get_runtime
from coin_cl.testing import look_at_camera, random_gaussians

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel

SMALL = small_mode()
N = 60 if SMALL else 800
W, H = (40, 24) if SMALL else (120, 77)


def _limited(raster="gpu", **limits) -> Runtime:
    """A fresh runtime on the default device whose queried limits are replaced by `limits`."""
    rt = Runtime(get_runtime().device)
    rt.limits = dataclasses.replace(rt.limits, **limits)
    rt.raster, rt.poison = raster, True
    return rt


def _case(seed=5, channels=3):
    gs = random_gaussians(N, seed=seed, channels=channels, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55, cx=W * 0.47, cy=H * 0.55)
    m2, con, dep, rad = reference.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
    return [t.float().double() for t in (m2, con, gs.opacities, gs.colors, dep)] + [rad]


def _fwd_bwd(mod, rt, inputs, det=True):
    m2, con, op, feat, dep, rad = inputs
    xs = [t.clone().requires_grad_(True) for t in (m2, con, op, feat)]
    kw = {"device": rt} if rt is not None else {}
    if rt is not None:
        rt.deterministic = det
    img, alpha = mod.rasterize_to_pixels(*xs, dep, rad, W, H, **kw)
    g = torch.Generator().manual_seed(70)
    cot = [
        torch.randn(img.shape, generator=g, dtype=torch.float64),
        torch.randn(alpha.shape, generator=g, dtype=torch.float64),
    ]
    grads = torch.autograd.grad([img, alpha], xs, [c.to(img.dtype) for c in cot])
    return [img.detach(), alpha.detach(), *grads]


def _assert_matches_twin(got, want):
    # The tolerances of tests/test_ops.py: forward 1e-5 relative, gradients 5e-4 / 1e-4 / 2e-4 / 1e-4.
    torch.testing.assert_close(got[0].double(), want[0], rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(got[1].double(), want[1], rtol=1e-5, atol=2e-6)
    for what, a, e, tol in zip(
        ("means2d", "conics", "opacities", "colors"), got[2:], want[2:], (5e-4, 1e-4, 2e-4, 1e-4)
    ):
        err = (a.double() - e).abs().max() / e.abs().max().clamp_min(1e-12)
        assert err <= tol, f"{what}: max error {err:.3g} exceeds {tol}"


def _groups(rt):
    """{kernel: work-group width} chosen for the GPU rasterizer on `rt`."""
    return {key[1]: width for key, (width, _) in rt.variant_fits.items()}


def test_limits_are_queried_from_the_device():
    lim = query_limits(get_runtime().device)
    assert lim.max_work_group_size >= 1 and lim.local_mem_size > 0 and lim.max_mem_alloc_size > 0
    assert get_runtime().limits == lim


def test_local_bytes_model_matches_what_the_compiler_reports():
    """CL_KERNEL_LOCAL_MEM_SIZE of each built variant is what `raster_gpu_local_bytes` predicts
    (some compilers round up; none may use more than predicted plus alignment)."""
    rt = _limited()
    for g in (RASTER_GPU_GROUPS[0], RASTER_GPU_GROUPS[-1]):
        for kernel in ("rasterize_fwd", "rasterize_bwd"):
            defines = {"NUM_CHANNELS": 3, **({} if g == 256 else {"GROUP": g})}
            _, used = rt.kernel_limits("rasterize_gpu.cl", kernel, defines)
            assert used <= raster_gpu_local_bytes(kernel, g) + 64, (kernel, g, used)


@pytest.mark.parametrize("max_wg", [128, 64, 16] if not SMALL else [64, 16])
@pytest.mark.parametrize("det", [True, False], ids=["deterministic", "atomics"])
def test_narrow_work_group_variants_match_the_twin(max_wg, det):
    rt = _limited(max_work_group_size=max_wg)
    inputs = _case()
    got = _fwd_bwd(ops, rt, inputs, det)
    assert _groups(rt) == {"rasterize_fwd": max_wg, "rasterize_bwd": max_wg}
    _assert_matches_twin(got, _fwd_bwd(reference, None, inputs))


def test_narrow_variant_is_as_reproducible_as_the_wide_one():
    inputs = _case(seed=8)
    a = _fwd_bwd(ops, _limited(max_work_group_size=32), inputs)
    b = _fwd_bwd(ops, _limited(max_work_group_size=32), inputs)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


def test_local_memory_limit_picks_the_widest_variant_that_fits():
    # 6000 B: the forward fits at 128 (4612 B), the backward with its reduction rows only at 64.
    rt = _limited(local_mem_size=6000)
    inputs = _case(seed=6, channels=4)
    got = _fwd_bwd(ops, rt, inputs)
    assert _groups(rt) == {"rasterize_fwd": 128, "rasterize_bwd": 64}
    _assert_matches_twin(got, _fwd_bwd(reference, None, inputs))


def test_the_kernels_own_work_group_limit_is_respected(monkeypatch):
    """CL_KERNEL_WORK_GROUP_SIZE (register pressure) below 256 picks a narrower variant."""
    rt = _limited()
    real = rt.kernel_limits

    def kernel_limits(filename, name, defines=None):
        wg, local = real(filename, name, defines)
        return (min(wg, 64) if filename == "rasterize_gpu.cl" else wg), local

    monkeypatch.setattr(rt, "kernel_limits", kernel_limits)
    inputs = _case(seed=7)
    got = _fwd_bwd(ops, rt, inputs)
    assert _groups(rt) == {"rasterize_fwd": 64, "rasterize_bwd": 64}
    _assert_matches_twin(got, _fwd_bwd(reference, None, inputs))


@pytest.mark.parametrize(
    "limits, match",
    [
        ({"max_work_group_size": 8}, "work-group size / local memory"),
        ({"local_mem_size": 512}, "work-group size / local memory"),
    ],
)
def test_impossible_limits_are_a_clear_error(limits, match):
    rt = _limited(**limits)
    m2, con, op, feat, dep, rad = _case()
    with pytest.raises(DeviceLimitError, match=match) as info:
        ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, device=rt)
    msg = str(info.value)
    assert rt.device.name in msg and "COIN_CL_RASTER=cpu" in msg
    # the forward fails first; it names the narrowest variant's needs (16 work-items, its bytes)
    assert (
        f"{RASTER_GPU_GROUPS[-1]} / {raster_gpu_local_bytes('rasterize_fwd', RASTER_GPU_GROUPS[-1])}" in msg
    )


def test_per_item_kernels_narrow_their_work_group_and_give_the_same_result():
    """project, bin, reduce, decode and SSIM ask for 64 work-items; below that they run narrower."""
    wide, narrow = _limited(raster="cpu"), _limited(raster="cpu", max_work_group_size=16)
    gs = random_gaussians(N, seed=9, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    outs = []
    for rt in (wide, narrow):
        m2, con, dep, rad = ops.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H, device=rt)
        img, alpha = ops.rasterize_to_pixels(m2, con, gs.opacities, gs.colors, dep, rad, W, H, device=rt)
        s = ops.ssim_map(img[None], img[None].flip(1).contiguous(), device=rt)
        outs.append([m2, rad, img, alpha, s])
    for a, b in zip(*outs):
        assert torch.equal(a, b)


def test_narrowing_follows_the_source_not_the_drivers_local_memory_figure(monkeypatch):
    """NVIDIA's OpenCL (H200, driver 580.159) reported figures that made every per-item kernel look
    bound to its 64-wide group; whether a kernel may run narrower is read from its source."""
    assert runtime.group_bound("rasterize_gpu.cl")
    for f in ("bin.cl", "project.cl", "reduce.cl", "decode.cl", "ssim.cl", "warp.cl", "rasterize_cpu.cl"):
        assert not runtime.group_bound(f), f
    rt = _limited(raster="cpu", max_work_group_size=16)
    wg_and_local = rt.kernel_limits
    monkeypatch.setattr(rt, "kernel_limits", lambda *a: (wg_and_local(*a)[0], 1024))
    assert rt._fit_local("bin.cl", "bin_rects", None, (64,)) == (16,)
    assert rt._fit_local("project.cl", "project_fwd", None, (64,)) == (16,)


def test_a_kernel_fixed_to_a_width_above_the_limit_is_a_clear_error():
    rt = _limited(max_work_group_size=64)
    with pytest.raises(DeviceLimitError, match="rasterize_fwd.*no narrower variant.*COIN_CL_DEVICE"):
        rt._fit_local("rasterize_gpu.cl", "rasterize_fwd", {"NUM_CHANNELS": 3}, (256,))


def test_a_buffer_over_the_largest_allocation_is_a_clear_error():
    rt = _limited(raster="cpu", max_mem_alloc_size=1024)
    m2, con, op, feat, dep, rad = _case()
    with pytest.raises(DeviceLimitError, match="CL_DEVICE_MAX_MEM_ALLOC_SIZE.*1024.*fewer splats"):
        ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, device=rt)
