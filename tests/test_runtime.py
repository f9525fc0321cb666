"""The per-variant program cache and shared buffers of `coin_cl.engine.runtime` (device choice:
tests/test_devices.py)."""

import pytest
import torch

from coin_cl.engine import ops
from coin_cl.engine.ops.rasterize import raster_variant
from coin_cl.engine.runtime import Runtime, get_runtime
from coin_cl.testing import look_at_camera, random_gaussians

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel


def test_only_variants_in_use_are_compiled():
    rt = Runtime(get_runtime().device)
    gs = random_gaussians(20, seed=0, channels=5)
    viewmat, K = look_at_camera(32, 32)
    m2, con, dep, rad = ops.project(gs.means, gs.quats, gs.scales, viewmat, K, 32, 32, device=rt)
    for _ in range(2):
        ops.rasterize_to_pixels(m2, con, gs.opacities, gs.colors, dep, rad, 32, 32, device=rt)
    built = sorted((name, dict(defs).get("NUM_CHANNELS")) for name, defs in rt.programs)
    raster_src = raster_variant(rt)[0]  # rasterize_cpu.cl on a CPU, rasterize_gpu.cl on a GPU
    assert built == [("bin.cl", None), ("project.cl", None), (raster_src, 5)]


def test_zero_copy_and_explicit_transfer_agree():
    """On unified memory nothing crosses; the copying path (as on a discrete GPU) counts bytes."""
    gs = random_gaussians(100, seed=1)
    viewmat, K = look_at_camera(48, 40)
    outs = []
    for unified in (True, False):
        rt = Runtime(get_runtime().device)
        rt.unified = unified and rt.unified
        m2, con, dep, rad = ops.project(gs.means, gs.quats, gs.scales, viewmat, K, 48, 40, device=rt)
        img, _ = ops.rasterize_to_pixels(m2, con, gs.opacities, gs.colors, dep, rad, 48, 40, device=rt)
        outs.append(img)
        if rt.unified:
            assert rt.bytes_transferred == 0
        else:
            assert rt.bytes_transferred > img.numel() * 4
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)


def test_float_atomics_variant_is_used_where_the_device_has_them():
    rt = Runtime(get_runtime().device)
    rt.deterministic = False
    gs = random_gaussians(30, seed=2)
    viewmat, K = look_at_camera(32, 32)
    means = gs.means.clone().requires_grad_(True)
    m2, con, dep, rad = ops.project(means, gs.quats, gs.scales, viewmat, K, 32, 32, device=rt)
    img, alpha = ops.rasterize_to_pixels(m2, con, gs.opacities, gs.colors, dep, rad, 32, 32, device=rt)
    (img.sum() + alpha.sum()).backward()
    used = {
        bool(dict(defs).get("USE_FLOAT_ATOMICS"))
        for name, defs in rt.programs
        if name.startswith("rasterize")
    }
    assert used == {False, True} if rt.float_atomics else used == {False}
    assert torch.isfinite(means.grad).all()
