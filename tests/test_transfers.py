"""The discrete-memory path (coin_cl.engine.transfers, Runtime(discrete=True)): device-only buffers
with explicit copies in and out, as on a discrete GPU, forced here on the CPU device. Every op gives
the same result as on the unified (aliasing) path, and the copy counters are non-zero exactly on
the discrete path."""

import numpy as np
import pytest
import torch
from conftest import small_mode

from coin_cl.engine import ops
from coin_cl.engine.ops.warp import warp_features
from coin_cl.engine.runtime import Runtime, get_runtime
from coin_cl.engine.transfers import TransferStats
from coin_cl.testing import look_at_camera, random_gaussians

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel

SMALL = small_mode()
N = 40 if SMALL else 600
W, H = (36, 20) if SMALL else (100, 67)


@pytest.fixture(scope="module")
def runtimes():
    """(unified, discrete, discrete with page-locked staging) runtimes on the default device,
    outputs poisoned (NaN / INT32_MIN): on the discrete paths too, an element a kernel leaves
    unwritten shows."""
    from coin_cl.engine.devices import host_unified

    dev = get_runtime().device
    if not host_unified(dev):  # a discrete GPU: every other kernel test runs the discrete path
        pytest.skip(f"{get_runtime().name} has no host-unified memory: no aliasing path to compare with")
    trio = (
        Runtime(dev, discrete=False),
        Runtime(dev, discrete=True, pinned=False),
        Runtime(dev, discrete=True, pinned=True),
    )
    for r in trio:
        r.poison = True
    return trio


def _project(rt):
    gs = random_gaussians(N, seed=0, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    leaves = [t.clone().requires_grad_(True) for t in (gs.means, gs.quats, gs.scales)]
    m2, con, dep, rad = ops.project(*leaves, viewmat, K, W, H, device=rt)
    g = torch.autograd.grad([m2.sum() + con.sum() + dep.sum()], leaves)
    return [m2, con, dep, rad, *g]


def _scene(channels=3):
    gs = random_gaussians(N, seed=1, channels=channels, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    from coin_cl.engine import reference

    m2, con, dep, rad = reference.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
    return [t.float() for t in (m2, con, gs.opacities, gs.colors, dep)] + [rad]


def _bin(rt):
    m2, con, op, _, dep, rad = _scene()
    b = ops.bin_tiles(m2, con, op, dep, rad, W, H, device=rt)
    return [b.tile_start, b.tile_end, b.ids, b.pair_start, b.pair_slot, b.extents]


def _rasterize(rt, variant, det):
    rt.raster, rt.deterministic = variant, det
    try:
        m2, con, op, feat, dep, rad = _scene()
        xs = [t.clone().requires_grad_(True) for t in (m2, con, op, feat)]
        img, alpha = ops.rasterize_to_pixels(*xs[:4], dep, rad, W, H, device=rt)
        g = torch.Generator().manual_seed(3)
        cot = [torch.randn(img.shape, generator=g), torch.randn(alpha.shape, generator=g)]
        return [img, alpha, *torch.autograd.grad([img, alpha], xs, cot)]
    finally:
        rt.raster, rt.deterministic = None, True


def _warp(rt):
    g = torch.Generator().manual_seed(4)
    pts = torch.randn(N * 4, 3, generator=g)
    pts[:, 2] = 3 + torch.rand(N * 4, generator=g)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat2 = viewmat.clone()
    viewmat2[0, 3] = 0.1
    feat = torch.rand(H, W, 3, generator=g).requires_grad_(True)
    out, wt, depth = warp_features(pts, K, viewmat, feat, K, viewmat2, W, H, device=rt)
    (grad,) = torch.autograd.grad(out, feat, torch.randn(out.shape, generator=g))
    return [out, wt, depth, grad]


def _decode(rt):
    g = torch.Generator().manual_seed(5)
    a, k = 30, 4
    vidx = torch.arange(0, a, 2)
    v = vidx.numel()
    leaves = [
        (torch.randn(a, k, 3, generator=g)).requires_grad_(True),
        (torch.randn(a, 6, generator=g) * 0.5 - 2).requires_grad_(True),
        torch.tanh(torch.randn(v * k, generator=g)).requires_grad_(True),
        torch.randn(v * k, 7, generator=g).requires_grad_(True),
        torch.rand(v * k, 3, generator=g).requires_grad_(True),
    ]
    sidx = (leaves[2] > 0).nonzero().squeeze(1)
    outs = ops.decode_neural_gaussians(torch.randn(a, 3, generator=g), *leaves, vidx, sidx, device=rt)
    grads = torch.autograd.grad(sum(o.sum() for o in outs), leaves, allow_unused=True)
    return [*outs, *[x for x in grads if x is not None]]


def _ssim(rt):
    g = torch.Generator().manual_seed(6)
    a = torch.rand(2, H, W, 3, generator=g).requires_grad_(True)
    b = torch.rand(2, H, W, 3, generator=g)
    s = ops.ssim_map(a, b, device=rt)
    (grad,) = torch.autograd.grad(s.sum(), a)
    return [s, grad]


def _chain(rt):
    """project -> bin -> rasterize and back: the ops read what the one before left on the device."""
    gs = random_gaussians(N, seed=7, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    leaves = [
        t.float().requires_grad_(True) for t in (gs.means, gs.quats, gs.scales, gs.opacities, gs.colors)
    ]
    m2, con, dep, rad = ops.project(*leaves[:3], viewmat, K, W, H, device=rt)
    img, alpha = ops.rasterize_to_pixels(m2, con, leaves[3], leaves[4], dep, rad, W, H, device=rt)
    g = torch.Generator().manual_seed(8)
    cot = [torch.randn(img.shape, generator=g), torch.randn(alpha.shape, generator=g)]
    return [img, alpha, *torch.autograd.grad([img, alpha], leaves, cot)]


OPS = {
    "project fwd+bwd": _project,
    "project, bin, rasterize fwd+bwd": _chain,
    "bin": _bin,
    "rasterize cpu fwd+bwd (deterministic)": lambda rt: _rasterize(rt, "cpu", True),
    "rasterize gpu fwd+bwd (deterministic)": lambda rt: _rasterize(rt, "gpu", True),
    "rasterize cpu fwd+bwd (atomics)": lambda rt: _rasterize(rt, "cpu", False),
    "rasterize gpu fwd+bwd (atomics)": lambda rt: _rasterize(rt, "gpu", False),
    "warp fwd+bwd": _warp,
    "decode fwd+bwd": _decode,
    "ssim fwd+bwd": _ssim,
}


@pytest.mark.parametrize("op", list(OPS))
def test_every_op_gives_the_same_result_on_both_paths_and_counts_copies_only_when_discrete(runtimes, op):
    results, crossed = [], []
    for rt in runtimes:
        before = rt.transfers.snapshot()
        results.append([t.detach() for t in OPS[op](rt)])
        crossed.append(TransferStats.delta(rt.transfers.snapshot(), before))
    unified = results[0]
    for path, discrete in zip(("discrete", "pinned"), results[1:], strict=True):
        for i, (u, d) in enumerate(zip(unified, discrete, strict=True)):
            assert u.shape == d.shape and u.dtype == d.dtype, f"{op} output {i}"
            if u.dtype.is_floating_point:
                assert torch.isfinite(d).all(), f"{op} output {i}: non-finite on the {path} path"
            if "atomics" in op:  # the order of the atomic adds differs run to run
                torch.testing.assert_close(d, u, rtol=1e-5, atol=1e-6, msg=f"{op} output {i}")
            else:
                assert torch.equal(d, u), f"{op} output {i} differs between the unified and {path} paths"
    on_unified = crossed[0]
    assert on_unified == {k: 0 for k in on_unified}, f"{op}: the unified path copied {on_unified}"
    assert crossed[1] == crossed[2] | {"seconds": crossed[1]["seconds"]}, "staging changed what crosses"
    for rt, on_discrete in zip(runtimes[1:], crossed[1:], strict=True):
        assert on_discrete["bytes_in"] > 0 and on_discrete["bytes_out"] > 0 and on_discrete["copies"] > 0
        assert not rt.transfers._pending  # every copy's event was timed at the finish
        if "oclgrind" not in rt.name.lower():  # the simulator's clock may not move in a copy
            assert on_discrete["seconds"] > 0.0, "copy time not measured on the discrete path"
    assert not runtimes[2]._blocks and runtimes[2]._pool.held > 0  # staged, and every block returned


def test_discrete_path_is_chosen_without_host_unified_memory_or_when_forced(monkeypatch):
    from coin_cl.engine import devices

    dev = get_runtime().device
    monkeypatch.delenv("COIN_CL_DISCRETE", raising=False)
    monkeypatch.delenv("COIN_CL_NO_ZERO_COPY", raising=False)
    assert Runtime(dev).discrete is (not devices.host_unified(dev))
    monkeypatch.setattr(devices, "host_unified", lambda d: False)  # as a discrete GPU reports
    rt = Runtime(dev)
    assert rt.discrete and not rt.unified
    monkeypatch.setattr(devices, "host_unified", lambda d: True)
    assert Runtime(dev).unified
    monkeypatch.setenv("COIN_CL_DISCRETE", "1")
    assert Runtime(dev).discrete
    assert Runtime(dev, discrete=False).unified  # an explicit choice wins over the variable


def test_bytes_counted_are_the_tensors_that_cross():
    """A one-kernel op on the discrete path copies exactly its inputs in and its outputs out."""
    rt = Runtime(get_runtime().device, discrete=True)
    a = torch.rand(1, 8, 9, 1)
    b = torch.rand(1, 8, 9, 1)
    ops.ssim_map(a, b, device=rt)
    n = a.numel()
    window = 11
    # in: a, b and the 11-tap window (float32), which both launches read and so crosses twice
    # (each launch wraps its own arguments); out: the SSIM map and 3 planar partials per channel.
    assert rt.transfers.bytes_in == 4 * (2 * n + 2 * window)
    assert rt.transfers.bytes_out == 4 * (n + 3 * n)
    assert rt.bytes_transferred == rt.transfers.bytes


def test_outputs_left_on_the_device_are_read_again_without_a_copy():
    """Binning and rasterizing what `project` returned read its buffers: of the splats only the
    opacities (an input, not an output) cross again."""
    rt = Runtime(get_runtime().device, discrete=True)
    gs = random_gaussians(N, seed=2, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    m2, con, dep, rad = ops.project(
        *[t.float() for t in (gs.means, gs.quats, gs.scales)], viewmat, K, W, H, device=rt
    )
    before = rt.transfers.snapshot()
    bins = ops.bin_tiles(m2, con, gs.opacities.float(), dep, rad, W, H, device=rt)
    crossed = TransferStats.delta(rt.transfers.snapshot(), before)
    assert crossed["reused"] == 4 * (m2.numel() + con.numel() + rad.numel())
    # in: the opacities, the depth order of the visible splats and the pair offsets
    assert crossed["bytes_in"] == 4 * (N + bins.n_visible + N + 1)
    fresh = ops.bin_tiles(m2.clone(), con.clone(), gs.opacities.float(), dep, rad.clone(), W, H, device=rt)
    for name in ("tile_start", "tile_end", "ids", "pair_slot", "extents"):
        assert torch.equal(getattr(bins, name), getattr(fresh, name)), name


def test_a_remembered_tensor_changed_since_is_copied_again():
    """An in-place change (torch advances the version counter) or a kernel writing into the
    tensor again makes the device copy stale: the next op copies the tensor in again."""
    rt = Runtime(get_runtime().device, discrete=True)
    gs = random_gaussians(N, seed=3, spread=1.2)
    viewmat, K = look_at_camera(W, H, fov_deg=55)
    m2, con, dep, rad = ops.project(
        *[t.float() for t in (gs.means, gs.quats, gs.scales)], viewmat, K, W, H, device=rt
    )
    m2 += 5.0  # every splat moves 5 px
    bins = ops.bin_tiles(m2, con, gs.opacities.float(), dep, rad, W, H, device=rt)
    fresh = ops.bin_tiles(m2.clone(), con.clone(), gs.opacities.float(), dep, rad.clone(), W, H, device=rt)
    assert torch.equal(bins.ids, fresh.ids) and torch.equal(bins.tile_start, fresh.tile_start)
    before = rt.transfers.reused
    assert rt.input(con).buf is not None and rt.transfers.reused == before + 4 * con.numel()
    rt.array(con, "out")  # a launch is about to write it: the remembered buffer is forgotten
    before = rt.transfers.bytes_in
    rt.input(con)
    assert rt.transfers.bytes_in == before + 4 * con.numel()


def test_page_locked_blocks_are_reused_and_a_full_pool_copies_directly():
    from coin_cl.engine.pinned import MIN_BLOCK

    rt = Runtime(get_runtime().device, discrete=True, pinned=True)
    from coin_cl.engine.devices import host_unified

    if host_unified(rt.device):  # the aliasing path copies nothing, so it stages nothing
        assert Runtime(rt.device, discrete=False, pinned=True).pinned is False
    a, b = torch.rand(1, 8, 9, 1), torch.rand(1, 8, 9, 1)
    first = ops.ssim_map(a, b, device=rt)
    assert first.data_ptr() in rt._pinned_ptrs  # the output itself lives in a page-locked block
    expected = first.clone()
    del first  # its block goes back to the pool
    held = rt._pool.held
    assert held >= MIN_BLOCK and held % MIN_BLOCK == 0
    again = ops.ssim_map(a, b, device=rt)
    assert torch.equal(again, expected) and rt._pool.held == held  # the blocks were reused
    rt._pool.max_bytes = held  # no room for the larger blocks of a larger image: direct copies
    a2, b2 = torch.rand(1, 300, 200, 1), torch.rand(1, 300, 200, 1)
    ref = Runtime(get_runtime().device, discrete=True, pinned=False)
    assert torch.equal(ops.ssim_map(a2, b2, device=rt), ops.ssim_map(a2, b2, device=ref))
    assert rt._pool.held == held


def test_an_accumulator_must_start_at_zero():
    """mode="acc" and mode="zeros" promise zeros (the discrete path fills the device buffer
    instead of copying them); with poisoning on, as in the tests, the promise is checked."""
    rt = Runtime(get_runtime().device, discrete=True)
    rt.poison = True
    for mode in ("acc", "zeros"):
        with pytest.raises(ValueError, match=f"mode='{mode}'.*zeros"):
            rt.array(torch.ones(4), mode=mode)
    acc, work = rt.array(torch.zeros(4), mode="acc"), rt.array(torch.zeros(4), mode="zeros")
    assert acc.copy_back and not work.copy_back and rt.transfers.bytes_in == 0  # nothing crossed


def test_zeros_are_filled_on_the_device_whatever_the_host_tensor_holds():
    """`Runtime.zeros` on the discrete path writes no host tensor: the device buffer is zero even
    when the tensor beside it holds garbage, and nothing crosses."""
    import pyopencl as cl

    rt = Runtime(get_runtime().device, discrete=True)
    work = rt.zeros(1000, dtype=torch.int32)
    work.tensor.fill_(7)  # what an uninitialised tensor could hold; the buffer must not care
    back = np.full(1000, -1, np.int32)
    cl.enqueue_copy(rt.queue, back, work.buf, is_blocking=True)
    assert not back.any() and rt.transfers.bytes_in == 0


def test_the_aliasing_path_is_refused_without_host_unified_memory(monkeypatch):
    from coin_cl.engine import devices

    monkeypatch.setattr(devices, "host_unified", lambda d: False)
    with pytest.raises(ValueError, match="no host-unified memory: it runs the discrete path only"):
        Runtime(get_runtime().device, discrete=False)
