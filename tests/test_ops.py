"""OpenCL kernels (coin_cl.engine.ops) against their float64 torch twins (coin_cl.engine.reference)."""

import numpy as np
import pytest
import torch
from conftest import small_mode

from coin_cl.engine import ops, reference
from coin_cl.engine.runtime import get_runtime
from coin_cl.testing import look_at_camera, random_gaussians

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel

SMALL = small_mode()
N = 60 if SMALL else 1500
W, H = (40, 24) if SMALL else (150, 97)  # non-multiples of the tile size on purpose


@pytest.fixture(params=["cpu", "gpu"])
def rt(request):
    """The runtime with each rasterizer variant in turn (both run on any OpenCL device)."""
    r = get_runtime()
    r.poison = True  # every output starts as NaN / INT32_MIN: an unwritten element shows
    r.raster = request.param
    yield r
    r.poison, r.raster, r.deterministic = False, None, True


def _camera(seed):
    g = torch.Generator().manual_seed(seed)
    viewmat, K = look_at_camera(W, H, fov_deg=55, cx=W * 0.47, cy=H * 0.55)  # off-centre
    viewmat[:3, 3] += 0.1 * torch.randn(3, generator=g, dtype=torch.float64)
    return viewmat, K


def assert_rel(actual, expected, rtol, what, atol_frac=None):
    """max |a - e| <= rtol * max(|e|) (+ elementwise check on finiteness)."""
    assert torch.isfinite(actual).all(), f"{what}: non-finite values"
    scale = expected.abs().max().clamp_min(1e-12)
    err = (actual.to(expected.dtype) - expected).abs().max() / scale
    assert err <= rtol, f"{what}: max error {err:.3g} of max |ref| {scale:.3g} exceeds {rtol}"


@pytest.mark.parametrize("seed", [0, 1])
def test_project_forward(rt, seed):
    gs = random_gaussians(N, seed=seed, spread=1.5)
    viewmat, K = _camera(seed)
    m2, con, dep, rad = ops.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
    rm2, rcon, rdep, rrad = reference.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
    for t in (m2, con, dep):
        assert torch.isfinite(t).all()
    assert (rad != torch.iinfo(torch.int32).min).all()
    # culling decisions agree except where a radius sits on an integer (float32 vs float64 ceil)
    both = (rad > 0) & (rrad > 0)
    assert (rad > 0).sum() > N // 4
    assert ((rad > 0) != (rrad > 0)).sum() <= max(1, N // 500)
    assert (rad[both] - rrad[both]).abs().max() <= 1
    torch.testing.assert_close(m2[both].double(), rm2[both], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(dep[both].double(), rdep[both], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(con[both].double(), rcon[both], rtol=2e-4, atol=1e-6)


def test_project_backward(rt):
    gs = random_gaussians(N, seed=3, spread=1.5).requires_grad_()
    viewmat, K = _camera(3)
    g = torch.Generator().manual_seed(30)
    outs = {}
    for name, fn in (("cl", ops.project), ("ref", reference.project)):
        m2, con, dep, rad = fn(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
        if name == "cl":
            keep = (rad > 0).double()
            v = [torch.randn(t.shape, generator=g, dtype=torch.float64) for t in (m2, con, dep)]
        v_keep = [v[0] * keep[:, None], v[1] * keep[:, None], v[2] * keep]
        grads = torch.autograd.grad([m2, con, dep], [gs.means, gs.quats, gs.scales], v_keep)
        outs[name] = grads
    for what, a, e, tol in zip(("means", "quats", "scales"), outs["cl"], outs["ref"], (2e-4, 2e-4, 2e-4)):
        assert_rel(a, e, tol, what)


def _projected(seed, n=N, channels=3):
    gs = random_gaussians(n, seed=seed, channels=channels, spread=1.2)
    viewmat, K = _camera(seed)
    m2, con, dep, rad = reference.project(gs.means, gs.quats, gs.scales, viewmat, K, W, H)
    # The kernels see float32 inputs; hand the twin exactly those values in float64.
    f = [t.float().double() for t in (m2, con, gs.opacities, gs.colors, dep)]
    return (*f, rad)


@pytest.mark.parametrize("channels", [1, 3, 4, 32] if not SMALL else [3])
def test_rasterize_forward(rt, channels):
    m2, con, op, feat, dep, rad = _projected(5, channels=channels)
    bg = torch.rand(channels, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    stats = {}
    img, alpha = ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, bg, stats=stats)
    rimg, ralpha = reference.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, bg)
    assert img.shape == (H, W, channels) and alpha.shape == (H, W)
    assert stats["n_pairs"] > 0
    torch.testing.assert_close(img, rimg, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(alpha, ralpha, rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("det", [1, 0], ids=["deterministic", "atomics"])
def test_rasterize_backward(rt, det):
    rt.deterministic = bool(det)
    m2, con, op, feat, dep, rad = _projected(7, channels=3)
    bg = torch.rand(3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    inputs = [m2, con, op, feat, bg]
    g = torch.Generator().manual_seed(70)
    v_img = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    v_alpha = torch.randn(H, W, generator=g, dtype=torch.float64)
    grads = {}
    for name, mod in (("cl", ops), ("ref", reference)):
        xs = [t.clone().requires_grad_(True) for t in inputs]
        img, alpha = mod.rasterize_to_pixels(xs[0], xs[1], xs[2], xs[3], dep, rad, W, H, xs[4])
        grads[name] = torch.autograd.grad([img, alpha], xs, [v_img, v_alpha])
    # Tolerances at least as tight as gsplat's tests (5e-3 means2d, 1e-3 conics/colours, 2e-3 opacity).
    tols = {"means2d": 5e-4, "conics": 1e-4, "opacities": 2e-4, "colors": 1e-4, "background": 1e-5}
    for (what, tol), a, e in zip(tols.items(), grads["cl"], grads["ref"]):
        assert_rel(a, e, tol, what)


def test_rasterize_depth_channel_and_many_channels(rt):
    """Features of 64 channels (DINO-like) plus depth through the public op."""
    m2, con, op, feat, dep, rad = _projected(9, channels=64 if not SMALL else 5)
    feat = torch.cat([feat, dep[:, None]], 1)
    img, _ = ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H)
    rimg, _ = reference.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H)
    torch.testing.assert_close(img, rimg, rtol=1e-5, atol=2e-5)


def test_float_vs_double_accumulation_knob(rt):
    """ACC_DOUBLE changes only the accumulation precision of the backward."""
    m2, con, op, feat, dep, rad = _projected(11)
    g = torch.Generator().manual_seed(3)
    v_img = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    res = []
    for defines in ({}, {"ACC_DOUBLE": 1}):
        x = feat.clone().requires_grad_(True)
        img, _ = ops.rasterize_to_pixels(m2, con, op, x, dep, rad, W, H, defines=defines)
        res.append(torch.autograd.grad(img, x, v_img)[0])
    assert_rel(res[1], res[0], 1e-5, "colors (double vs float accumulation)")


def test_bins_are_depth_ordered_and_complete(rt):
    """Every tile's list is the depth-ordered set of splats whose tile rectangle covers it."""
    m2, con, op, feat, dep, rad = _projected(13)
    f32 = [t.float().contiguous() for t in (m2, con, op)]
    bins = ops.bin_tiles(*f32, dep.float(), rad.int(), W, H, max_pairs=1 << 30, device=rt)
    rect = reference.tile_rects(m2, rad, bins.tiles_x, bins.tiles_y)
    for t in range(bins.tiles_x * bins.tiles_y):
        ids = bins.ids[bins.tile_start[t] : bins.tile_end[t]].long()
        d = dep[ids]
        assert (d[1:] >= d[:-1]).all(), f"tile {t} not depth-ordered"
        tx, ty = t % bins.tiles_x, t // bins.tiles_x
        covers = (rect[ids, 0] <= tx) & (tx < rect[ids, 2]) & (rect[ids, 1] <= ty) & (ty < rect[ids, 3])
        assert covers.all(), f"tile {t} holds a splat outside its 3-sigma rectangle"
    assert bins.n_pairs == bins.ids.numel()


def test_stable_depth_order_is_a_stable_argsort_with_ties_signed_zeros_and_nan():
    from coin_cl.engine.ops.bin import stable_depth_order

    rng = np.random.default_rng(0)
    neg_nan = np.array([0x7FC00000 | 0x80000000], np.uint32).view(np.float32)[0]
    cases = [
        rng.normal(size=2000).astype(np.float32),
        np.round(rng.normal(size=3000), 1).astype(np.float32),  # many ties, -0.0 among them
        np.array([0.0, -0.0, 1, 1, np.inf, -np.inf, np.nan, -1e-40, 1e-40, 2, neg_nan], np.float32),
        np.full(5, 3.0, np.float32),
        np.zeros(0, np.float32),
    ]
    for d in cases:
        got = stable_depth_order(torch.from_numpy(d))
        assert got.dtype == torch.int64
        assert np.array_equal(got.numpy(), np.argsort(d, kind="stable"))
        # Only the kept ones, mostly kept (cut after the sort) and mostly dropped (gathered first).
        for frac in (0.8, 0.3, 0.0, 1.0):
            keep = rng.random(d.size) < frac
            kept = np.flatnonzero(keep)
            got = stable_depth_order(torch.from_numpy(d), keep=torch.from_numpy(keep))
            assert np.array_equal(got.numpy(), kept[np.argsort(d[kept], kind="stable")]), frac


@pytest.mark.parametrize("seed", [13, 14])
def test_bins_match_the_twin(rt, seed):
    """bin_tiles (kernels) and its twin give the same tile lists, pair slots and extents."""
    rt.poison = True
    try:
        m2, con, op, feat, dep, rad = _projected(seed)
        f32 = [t.float().contiguous() for t in (m2, con, op, dep)]
        got = ops.bin_tiles(*f32, rad.int(), W, H, max_pairs=1 << 30, device=rt)
    finally:
        rt.poison = False
    want = reference.bin_tiles(*f32, rad.int(), W, H, max_pairs=1 << 30)
    assert (got.tiles_x, got.tiles_y, got.n_pairs, got.n_visible) == (
        want.tiles_x, want.tiles_y, want.n_pairs, want.n_visible)  # fmt: skip
    assert got.n_pairs > 0
    for name in ("tile_start", "tile_end", "ids", "pair_start", "pair_slot"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    assert_rel(got.extents, want.extents, 1e-5, "extents")


def test_given_bins_give_the_same_image(rt):
    """Binning once and passing the bins to several passes changes nothing."""
    m2, con, op, feat, dep, rad = _projected(15)
    bins = ops.bin_tiles(m2, con, op, dep, rad, W, H, device=rt)
    a = ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, device=rt)
    b = ops.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, device=rt, bins=bins)
    c = reference.rasterize_to_pixels(m2, con, op, feat, dep, rad, W, H, bins=bins)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    assert_rel(a[0], c[0], 1e-5, "image through the twin with kernel bins")


def test_cpu_kernel_exp_matches_float64():
    """The CPU rasterizer's operator-only exp (PoCL does not inline the built-in) is as accurate
    as the built-in: relative error under 2e-7 over the whole range compositing uses."""
    import pyopencl as cl

    from coin_cl.engine.devices import kernel_dir

    r = get_runtime()
    src = (kernel_dir() / "rasterize_cpu.cl").read_text()
    fn = src[src.index("inline float8 exp_neg8") : src.index("#ifndef EXPF")]
    prg = cl.Program(r.context, fn + "__kernel void t(__global const float8 *x, __global float8 *y)"
                     "{ y[get_global_id(0)] = exp_neg8(x[get_global_id(0)]); }").build()  # fmt: skip
    g = np.random.default_rng(0)
    x = np.concatenate([-g.random(8000) * 2, -g.random(8000) * 90, [0.0] * 8]).astype(np.float32)
    y = np.empty_like(x)
    mf = cl.mem_flags
    bx = cl.Buffer(r.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    by = cl.Buffer(r.context, mf.WRITE_ONLY, y.nbytes)
    prg.t(r.queue, (x.size // 8,), None, bx, by)
    cl.enqueue_copy(r.queue, y, by)
    ref = np.exp(np.maximum(x.astype(np.float64), -87.0))
    assert np.all(np.abs(y - ref) <= 2e-7 * ref)


def test_deterministic_backward_is_bit_reproducible(rt):
    """Fixed-order gradient sums: the same inputs give bit-identical gradients, run after run."""
    m2, con, op, feat, dep, rad = _projected(15, channels=4)
    g = torch.Generator().manual_seed(5)
    v_img = torch.randn(H, W, 4, generator=g)
    runs = []
    for _ in range(3):
        xs = [t.float().clone().requires_grad_(True) for t in (m2, con, op, feat)]
        img, _ = ops.rasterize_to_pixels(xs[0], xs[1], xs[2], xs[3], dep, rad, W, H)
        runs.append(torch.autograd.grad(img, xs, v_img))
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            assert torch.equal(a, b)


@pytest.fixture(scope="module")
def real_geometry(spinnerf_dir):
    """The shared scene's SfM points and the real camera of view 0 (K scaled to a smaller image),
    with seeded scales, rotations, opacities and colours as gsplat's tests do with its garden data."""

    from coin_cl.scene.conventions import invert_rigid, llff_to_camtoworld
    from coin_cl.scene.ply import read_points_ply
    from coin_cl.testing import garden_like

    pts, _ = read_points_ply(spinnerf_dir / "sparse" / "0" / "points3D.ply")
    c2w, hwf, _ = llff_to_camtoworld(np.load(spinnerf_dir / "poses_bounds.npy"))
    w, h = (63, 36) if SMALL else (252, 142)
    f = hwf[0, 2] / 4 * w / 1008
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=torch.float64)
    viewmat = torch.tensor(invert_rigid(c2w[0]), dtype=torch.float64)
    gs = garden_like(torch.from_numpy(pts), 300 if SMALL else 5000, seed=3)
    gs.scales *= 20  # a few pixels wide at this resolution, so splats overlap
    return gs, viewmat, K, w, h


def test_real_geometry_forward_and_gradients(rt, real_geometry):
    gs, viewmat, K, w, h = real_geometry
    m2, con, dep, rad = ops.project(gs.means, gs.quats, gs.scales, viewmat, K, w, h)
    rm2, rcon, rdep, rrad = reference.project(
        *(t.double() for t in (gs.means, gs.quats, gs.scales)), viewmat, K, w, h
    )
    both = (rad > 0) & (rrad > 0)
    assert both.sum() > gs.means.shape[0] // 4, "the real camera should see most SfM points"
    torch.testing.assert_close(m2[both].double(), rm2[both], rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(dep[both].double(), rdep[both], rtol=1e-5, atol=1e-5)
    inputs = [t.double() for t in (m2, con, gs.opacities, gs.colors)]
    g = torch.Generator().manual_seed(9)
    v_img = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    out = {}
    for name, mod in (("cl", ops), ("ref", reference)):
        xs = [t.clone().requires_grad_(True) for t in inputs]
        img, alpha = mod.rasterize_to_pixels(xs[0], xs[1], xs[2], xs[3], dep.double(), rad, w, h)
        out[name] = (img.detach(), torch.autograd.grad(img, xs, v_img))
    torch.testing.assert_close(out["cl"][0], out["ref"][0], rtol=1e-5, atol=2e-6)
    for what, a, e in zip(("means2d", "conics", "opacities", "colors"), out["cl"][1], out["ref"][1]):
        assert_rel(a, e, 5e-4, what)
