"""Feature warping (coin_cl.warp, kernels/warp.cl) against its float64 twin, analytic geometry
(a textured plane: the homography warp) and the stiff cases."""

import math

import cv2
import numpy as np
import pytest
import torch
from conftest import small_mode

from coin_cl.engine import reference_warp as warp_reference
from coin_cl.engine.ops import warp
from coin_cl.engine.runtime import get_runtime
from coin_cl.scene import Camera
from coin_cl.scene.conventions import interpolate_pose, make_viewmat, quat_wxyz_to_rotmat

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel

SMALL = small_mode()
W, H = (23, 17) if SMALL else (97, 61)  # non-multiples of the tile size on purpose
M = 250 if SMALL else 5000
CHANNELS = [1, 3, 64] if not SMALL else [1, 3, 9]


@pytest.fixture
def rt():
    r = get_runtime()
    r.poison = True  # outputs start as NaN / INT32_MIN: an unwritten element shows
    yield r
    r.poison = False


def _f32(t):
    """float64 holding float32-exact values: the kernels and the twin then see the same inputs."""
    return torch.as_tensor(t, dtype=torch.float64).float().double()


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return quat_wxyz_to_rotmat(np.concatenate([[math.cos(h)], math.sin(h) * axis]))


def _cameras(w=W, h=H, w2=None, h2=None):
    """A source camera at the origin and a target rotated 6 degrees and moved sideways."""
    f = 0.9 * w
    K1 = _f32([[f, 0, w * 0.48], [0, f * 1.02, h * 0.53], [0, 0, 1]])
    w2, h2 = w2 or w + 5, h2 or h - 3
    K2 = _f32([[f, 0, w2 * 0.5], [0, f, h2 * 0.5], [0, 0, 1]])
    V1 = _f32(make_viewmat(_rot([0.1, 1, 0], -2), [0.05, 0, 0]))
    V2 = _f32(make_viewmat(_rot([0.2, 1, 0.1], 6), [-0.3, 0.05, 0.1]))
    return K1, V1, K2, V2, w2, h2


def _pix(P, K, V):
    pc = P @ V[:3, :3].T + V[:3, 3]
    return K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2], pc[:, 2]


def _away_from_boundaries(P, cams, D=None, tol=0.01):
    """Drop points within 1e-3 px of a pixel edge or centre line, or within 1e-4 of the occlusion
    threshold: there float32 and float64 may legitimately decide differently (another pixel,
    another visibility), which is not what these comparisons are about."""
    keep = torch.ones(P.shape[0], dtype=torch.bool)
    for K, V in cams:
        u, v, _ = _pix(P, K, V)
        for c in (u, v):
            keep &= ((c - c.round()).abs() > 1e-3) & ((c - 0.5 - (c - 0.5).round()).abs() > 1e-3)
    if D is not None:
        K, V = cams[0]
        u, v, z = _pix(P, K, V)
        h, w = D.shape
        d = D[v.clamp(0, h - 1).floor().long(), u.clamp(0, w - 1).floor().long()]
        keep &= (z / (d * (1 + tol)) - 1).abs() > 1e-4
    return P[keep]


def _scene(seed, C, m=M, with_depth=True):
    g = torch.Generator().manual_seed(seed)
    K1, V1, K2, V2, w2, h2 = _cameras()
    P = torch.randn(m, 3, generator=g, dtype=torch.float64)
    P[:, :2] *= 1.1
    P[:, 2] = 3.0 + 2.5 * torch.rand(m, generator=g, dtype=torch.float64)
    P = _f32(P)
    F = _f32(torch.rand(H, W, C, generator=g, dtype=torch.float64) * 2 - 0.5)
    D = None
    if with_depth:  # a smooth rendered surface: points behind it are occluded in the source
        yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        D = _f32(4.6 + 0.5 * torch.sin(xx / 5.0) * torch.cos(yy / 4.0))
        D[0, 0] = 0.0  # an empty pixel: nothing occludes there
    P = _away_from_boundaries(P, [(K1, V1), (K2, V2)], D)
    return P, K1, V1, F, K2, V2, w2, h2, D


def _run(mod, P, K1, V1, F, K2, V2, w2, h2, D, grad=None, **kw):
    x = F.clone().requires_grad_(True)
    stats = {}
    out = mod.warp_features(P, K1, V1, x, K2, V2, w2, h2, src_depth=D, stats=stats, **kw)
    g = None
    if grad is not None:
        g = torch.autograd.grad(out[0], x, grad)[0]
    return [o.detach() for o in out], g, stats


def assert_rel(actual, expected, rtol, what):
    """max |a - e| <= rtol * max(|e|), and everything finite."""
    assert torch.isfinite(actual).all(), f"{what}: non-finite values"
    scale = expected.abs().max().clamp_min(1e-12)
    err = (actual.double() - expected).abs().max() / scale
    assert err <= rtol, f"{what}: max error {err:.3g} of max |ref| {scale:.3g} exceeds {rtol}"


def assert_features(f, wt, rf, rwt):
    """Features against the twin. Float32 pixel coordinates (~100) carry ~1e-5 px of error, and so
    do the bilinear weights; a pixel's mean divides by its weight sum, which amplifies that error
    where the sum is small (a point barely touching the pixel). So: the weighted sums everywhere,
    the means where the weight is at least 1/4 (nearly a whole point)."""
    w = rwt[..., None]
    assert_rel(f * wt[..., None], rf * w, 2e-5, "weighted features")
    full = rwt >= 0.25
    assert_rel(f[full], rf[full], 4e-5, "features (weight >= 1/4)")
    assert torch.isfinite(f).all()


@pytest.mark.parametrize("footprint", ["bilinear", "nearest"])
@pytest.mark.parametrize("channels", CHANNELS)
def test_forward_and_gradient_match_twin(rt, channels, footprint):
    scene = _scene(channels, channels)
    g = torch.Generator().manual_seed(100 + channels)
    w2, h2 = scene[6], scene[7]
    v = torch.randn(h2, w2, channels, generator=g, dtype=torch.float64)
    (f, wt, d), grad, st = _run(warp, *scene, grad=v, footprint=footprint)
    (rf, rwt, rd), rgrad, rst = _run(warp_reference, *scene, grad=v, footprint=footprint)
    assert f.shape == (h2, w2, channels) and wt.shape == (h2, w2) and d.shape == (h2, w2)
    assert torch.equal(st["status"], rst["status"]), "per-point decisions differ from the twin"
    assert st["n_ok"] > len(scene[0]) // 5 and st["n_occluded_src"] > 0 and st["n_outside_src"] > 0
    assert (wt > 0).sum() > 20
    assert_features(f, wt, rf, rwt)
    assert_rel(wt, rwt, 2e-5, "weight")
    assert_rel(d, rd, 1e-6, "depth")
    assert torch.equal(wt > 0, rwt > 0)
    assert_rel(grad, rgrad, 5e-5, "d src_features")  # w / weight-sum: see assert_features


def test_backward_is_bit_reproducible(rt):
    """Fixed-order sums: the same inputs give bit-identical gradients, run after run."""
    scene = _scene(7, 4)
    v = torch.randn(scene[7], scene[6], 4, generator=torch.Generator().manual_seed(1))
    runs = [_run(warp, *scene, grad=v)[1] for _ in range(3)]
    assert runs[0].abs().sum() > 0
    for other in runs[1:]:
        assert torch.equal(runs[0], other)


def test_without_source_depth_nothing_is_occluded(rt):
    scene = list(_scene(3, 3, with_depth=False))
    (f, wt, d), _, st = _run(warp, *scene)
    (rf, rwt, rd), _, rst = _run(warp_reference, *scene)
    assert st["n_occluded_src"] == 0 and torch.equal(st["status"], rst["status"])
    assert_features(f, wt, rf, rwt)
    assert_rel(d, rd, 1e-6, "depth")


# --------------------------------------------------------------------------- analytic geometry


def _smooth_texture(h, w, seed, sigma=3.0):
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, 3)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    img = (img - img.min()) / (img.max() - img.min())
    return img


def _plane_cameras(w, h):
    """Two real-looking cameras (1008x567's aspect and focal, scaled) facing a plane at z ~ 4, and
    the intermediate pose between them (the CLG target)."""
    f = 0.85 * w
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    k = Camera(K, make_viewmat(_rot([0, 1, 0], 4), [-0.2, 0.0, 0.0]), w, h, "k")
    n = Camera(K, make_viewmat(_rot([0.3, 1, 0], -12), [0.6, 0.1, 0.3]), w, h, "n")
    phi = Camera(K, interpolate_pose(k.viewmat, n.viewmat, 0.5), w, h, "phi")
    return k, n, phi


def _plane_points(cam, normal, d0, step):
    """Points of the plane {X: normal . X = d0} seen through cam's pixels at `step` px spacing."""
    us = np.arange(step / 2, cam.width, step)
    vs = np.arange(step / 2, cam.height, step)
    uu, vv = np.meshgrid(us, vs)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    rays = cam.unproject(uv, np.ones(len(uv))) - cam.center  # unit-depth rays
    t = (d0 - cam.center @ normal) / (rays @ normal)
    return cam.center + t[:, None] * rays


def _homography(src: Camera, dst: Camera, normal, d0):
    """3x3 H mapping dst pixel coordinates to src pixel coordinates (our convention) for the plane."""
    # four dst pixels, their plane points, their src pixels: an exact 4-point homography
    uv_d = np.array(
        [[10.0, 10.0], [dst.width - 10, 12.0], [dst.width - 12, dst.height - 9], [9.0, dst.height - 11]]
    )
    rays = dst.unproject(uv_d, np.ones(4)) - dst.center
    t = (d0 - dst.center @ normal) / (rays @ normal)
    uv_s, _ = src.project(dst.center + t[:, None] * rays)
    A = []
    for (x, y), (u, v) in zip(uv_d, uv_s):
        A.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        A.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, vt = np.linalg.svd(np.asarray(A))
    Hm = vt[-1].reshape(3, 3)
    return Hm / Hm[2, 2]


def test_plane_reproduces_homography_warp(rt):
    """Warping view k's image through points on a plane into the intermediate pose phi equals
    OpenCV's warpPerspective with the plane's homography, inside the covered region.

    Tolerance: the splat averages the source image at point positions within one target pixel of
    each pixel centre (bilinear footprint), a smoothing of about half a pixel: with a texture
    blurred by sigma = 3 px the mean error is below 0.004 and the worst pixel below 0.03 (values
    in [0, 1]); the nearest footprint, which lacks the centring, has about twice that."""
    w, h = (64, 36) if SMALL else (252, 142)
    k, _, phi = _plane_cameras(w, h)
    normal, d0 = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0]), 4.0
    pts = _plane_points(k, normal, d0, step=0.5)  # 4 points per source pixel, as an unprojected render
    img = _smooth_texture(h, w, seed=1)
    out, wt, depth = warp.warp_features(
        torch.from_numpy(pts), k.K, k.viewmat, torch.from_numpy(img), phi.K, phi.viewmat, w, h
    )
    Hm = _homography(k, phi, normal, d0)
    T = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]])  # OpenCV pixel centres are at integers
    Hcv = np.linalg.inv(T) @ Hm @ T
    ref = cv2.warpPerspective(img, Hcv, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    # covered region: full weight around the pixel (eroded by 2 px) and the preimage well inside k
    covered = cv2.erode((wt.numpy() > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    q = Hm @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    su, sv = (q[0] / q[2]).reshape(h, w), (q[1] / q[2]).reshape(h, w)
    covered &= (su > 2) & (su < w - 2) & (sv > 2) & (sv < h - 2)
    assert covered.mean() > 0.5
    err = np.abs(out.numpy() - ref)[covered]
    assert err.mean() < 0.004 and err.max() < 0.03, (err.mean(), err.max())
    # the z-buffer holds the plane's depth seen from phi
    rays = phi.unproject(np.stack([xs.ravel(), ys.ravel()], 1), np.ones(xs.size)) - phi.center
    t = (d0 - phi.center @ normal) / (rays @ normal)
    z_true = (t * (rays @ phi.viewmat[2, :3])).reshape(h, w)  # camera z of the plane point
    zerr = np.abs(depth.numpy() - z_true)[covered] / z_true[covered]
    assert zerr.max() < 0.01  # zmin of points up to one pixel away on a slanted plane


def test_occlusion_nearer_plane_wins(rt):
    """A small near patch (z = 2, value 1) in front of a far plane (z = 4, value 0), seen by a
    source camera; the target moves sideways. Where the patch projects, the near points win; the
    far plane visible in both views keeps its value; the strip of the far plane hidden behind
    the patch in the source but revealed in the target gets no correspondence when the source
    depth is given, and (the documented failure mode without it) the patch's value otherwise."""
    w, h = (40, 24) if SMALL else (120, 72)
    f = 0.8 * w
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    src = Camera(K, np.eye(4), w, h)
    shift = 1.0
    dst = Camera(K, make_viewmat(np.eye(3), [-shift, 0, 0]), w, h)  # centre at x = +shift
    half = 0.5  # patch: |x|, |y| < 0.5 at z = 2
    # source image and depth, analytically: ray through pixel hits the patch or the far plane
    xs, ys = np.meshgrid((np.arange(w) + 0.5 - w / 2) / f, (np.arange(h) + 0.5 - h / 2) / f)
    on_patch = (np.abs(2 * xs) < half) & (np.abs(2 * ys) < half)
    img = on_patch.astype(np.float32)[..., None]
    depth = np.where(on_patch, 2.0, 4.0).astype(np.float32)
    near = _plane_points(src, np.array([0, 0, 1.0]), 2.0, 0.5)
    near = near[(np.abs(near[:, 0]) < half) & (np.abs(near[:, 1]) < half)]
    far = _plane_points(src, np.array([0, 0, 1.0]), 4.0, 0.5)
    pts = torch.from_numpy(np.concatenate([near, far]))
    F = torch.from_numpy(img)
    st = {}
    out, wt, z = warp.warp_features(pts, src.K, src.viewmat, F, dst.K, dst.viewmat, w, h,
                                    src_depth=torch.from_numpy(depth), stats=st)  # fmt: skip
    out0, wt0, _ = warp.warp_features(pts, src.K, src.viewmat, F, dst.K, dst.viewmat, w, h)
    assert st["n_occluded_src"] > 0
    # target regions, analytically (u = f (X - shift) / Z + w/2)
    u = np.arange(w) + 0.5
    v = np.arange(h) + 0.5
    uu, vv = np.meshgrid(u, v)
    X2, Y2 = (uu - w / 2) / f * 2 + shift, (vv - h / 2) / f * 2  # patch plane point under the pixel
    X4, Y4 = (uu - w / 2) / f * 4 + shift, (vv - h / 2) / f * 4  # far plane point under the pixel
    patch_px = (np.abs(X2) < half - 0.1) & (np.abs(Y2) < half - 0.1)
    hidden_in_src = (np.abs(X4 / 2) < half - 0.1) & (np.abs(Y4 / 2) < half - 0.1)  # behind the patch
    revealed = hidden_in_src & ~((np.abs(X2) < half + 0.1) & (np.abs(Y2) < half + 0.1))
    visible_far = ~((np.abs(X4 / 2) < half + 0.1) & (np.abs(Y4 / 2) < half + 0.1)) & ~(
        (np.abs(X2) < half + 0.1) & (np.abs(Y2) < half + 0.1)
    )
    visible_far &= (np.abs(X4 / 4 * f) < w / 2 - 2) & (np.abs(Y4 / 4 * f) < h / 2 - 2)  # inside the source
    for o in (out, out0):
        assert patch_px.sum() > 10
        np.testing.assert_allclose(o[..., 0].numpy()[patch_px], 1.0, atol=1e-6)
        np.testing.assert_allclose(o[..., 0].numpy()[visible_far], 0.0, atol=1e-6)
    np.testing.assert_allclose(z.numpy()[patch_px], 2.0, rtol=1e-5)
    np.testing.assert_allclose(z.numpy()[visible_far], 4.0, rtol=1e-5)
    assert revealed.sum() > 5
    assert (wt.numpy()[revealed] == 0).all()  # with src_depth: a hole, honestly
    np.testing.assert_allclose(out0[..., 0].numpy()[revealed], 1.0, atol=1e-6)  # without: wrong colour


# --------------------------------------------------------------------------- stiff cases


def _simple(w=W, h=H):
    f = 0.9 * w
    K = _f32([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    return K, torch.eye(4, dtype=torch.float64)


def test_points_behind_either_camera_or_on_camera_plane(rt):
    K, V1 = _simple()
    V2 = _f32(make_viewmat(np.eye(3), [0, 0, -3.5]))  # target camera at z = 3.5, looking +z
    P = torch.tensor([
        [0.0, 0.0, 4.0],    # in front of both
        [0.1, 0.0, -1.0],   # behind the source
        [0.2, 0.1, 0.0],    # on the source camera plane
        [0.0, 0.0, 2.0],    # in front of the source, behind the target
        [0.05, 0.0, 3.5],   # on the target camera plane
    ], dtype=torch.float64)  # fmt: skip
    F = torch.rand(H, W, 2, dtype=torch.float64)
    for mod in (warp, warp_reference):
        st = {}
        out, wt, d = mod.warp_features(P, K, V1, F, K, V2, W, H, stats=st)
        assert st["status"].tolist() == [0, 2, 2, 5, 5], mod.__name__
        assert all(torch.isfinite(t).all() for t in (out, wt, d))
        assert wt.sum() > 0.999


def test_points_outside_images(rt):
    K, V = _simple()
    V2 = _f32(make_viewmat(np.eye(3), [-3.0, 0, 0]))  # target centre at x = 3
    P = torch.tensor(
        [[1.5, 0.0, 4.0], [50.0, 0.0, 4.0], [-0.9, 0.0, 4.0], [0.0, -30.0, 4.0]], dtype=torch.float64
    )
    F = torch.rand(H, W, 3, dtype=torch.float64)
    for mod in (warp, warp_reference):
        st = {}
        out, wt, _ = mod.warp_features(P, K, V, F, K, V2, W, H, stats=st)
        assert st["status"].tolist() == [0, 3, 6, 3]
        assert torch.isfinite(out).all()


def test_nonfinite_points_are_culled_and_counted(rt):
    scene = list(_scene(11, 3))
    P = scene[0].clone()
    P[::7, 0] = float("nan")
    P[3::11, 2] = float("inf")
    P[5::13, 1] = -float("inf")
    scene[0] = P
    bad = (~torch.isfinite(P).all(1)).sum().item()
    v = torch.randn(scene[7], scene[6], 3, dtype=torch.float64)
    (f, wt, d), g, st = _run(warp, *scene, grad=v)
    (rf, rwt, _), rg, rst = _run(warp_reference, *scene, grad=v)
    assert st["n_nonfinite"] == rst["n_nonfinite"] == bad > 0
    for t in (f, wt, d, g):
        assert torch.isfinite(t).all()
    assert_features(f, wt, rf, rwt)
    assert_rel(g, rg, 5e-5, "d src_features")


def test_huge_coordinates(rt):
    """A projection that overflows float32 is culled (as behind the camera: no finite pixel); a
    point at z = 3e38 is simply far away and valid; outputs stay finite."""
    K, V = _simple()
    P = torch.tensor([[3e38, 1.0, 4.0], [0.1, 0.1, 3e38], [0.0, 0.0, 4.0]], dtype=torch.float64)
    st = {}
    out, wt, d = warp.warp_features(P, K, V, torch.ones(H, W, 1), K, V, W, H, stats=st)
    assert st["status"].tolist() == [2, 0, 0]
    assert all(torch.isfinite(t).all() for t in (out, wt, d))
    assert d.max() == 4.0  # the near point wins the centre pixels, the far one is elsewhere


def test_empty_cloud(rt):
    K, V = _simple()
    F = torch.rand(H, W, 3, dtype=torch.float64, requires_grad=True)
    for mod in (warp, warp_reference):
        st = {}
        out, wt, d = mod.warp_features(torch.zeros(0, 3), K, V, F, K, V, W + 2, H, stats=st)
        assert st["n_points"] == 0
        assert out.shape == (H, W + 2, 3) and (out == 0).all() and (wt == 0).all() and (d == 0).all()
        (g,) = torch.autograd.grad(out, F, torch.ones_like(out))
        assert g.shape == F.shape and (g == 0).all()


@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_scene_scale_invariance(rt, scale):
    """Relative tolerances and no near plane: scaling points and camera centres leaves the
    features and coverage unchanged and scales the depth."""
    P, K1, V1, F, K2, V2, w2, h2, D = _scene(13, 3)
    base, _, _ = _run(warp, P, K1, V1, F, K2, V2, w2, h2, D)
    Vs1, Vs2 = V1.clone(), V2.clone()
    Vs1[:3, 3] *= scale
    Vs2[:3, 3] *= scale
    scaled, _, _ = _run(warp, P * scale, K1, Vs1, F, K2, Vs2, w2, h2, D * scale)
    assert_rel(scaled[0], base[0].double(), 1e-4, "features")
    assert_rel(scaled[1], base[1].double(), 1e-4, "weight")
    assert_rel(scaled[2] / scale, base[2].double(), 1e-4, "depth")


def test_one_by_one_target(rt):
    scene = list(_scene(17, 2))
    K2 = _f32([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])  # a 1x1 camera with a wide view
    scene[4], scene[6], scene[7] = K2, 1, 1
    v = torch.ones(1, 1, 2, dtype=torch.float64)
    (f, wt, d), g, st = _run(warp, *scene, grad=v)
    (rf, rwt, rd), rg, rst = _run(warp_reference, *scene, grad=v)
    assert f.shape == (1, 1, 2) and st["n_ok"] > 10 and wt.item() > 0
    assert_features(f, wt, rf, rwt)
    assert_rel(d, rd, 1e-6, "depth")
    assert_rel(g, rg, 5e-5, "d src_features")


def test_bad_input_is_a_clear_error(rt):
    K, V = _simple()
    P, F = torch.zeros(4, 3), torch.zeros(H, W, 3)
    bad_V = V.clone()
    bad_V[0, 3] = float("nan")
    cases = [
        (dict(points=torch.zeros(4, 2)), "points"),
        (dict(src_features=torch.zeros(H, W)), "src_features"),
        (dict(src_features=torch.zeros(H, W, 200)), "channels"),
        (dict(src_viewmat=bad_V), "NaN"),
        (dict(dst_K=torch.zeros(3, 3)), "focal"),
        (dict(dst_viewmat=torch.eye(3)), "shape"),
        (dict(src_depth=torch.zeros(H + 1, W)), "src_depth"),
        (dict(dst_width=0), "target size"),
        (dict(depth_tol=-1.0), "depth_tol"),
        (dict(footprint="gauss"), "footprint"),
    ]
    base = dict(points=P, src_K=K, src_viewmat=V, src_features=F, dst_K=K, dst_viewmat=V, dst_width=W,
                dst_height=H)  # fmt: skip
    for mod in (warp, warp_reference):
        for change, match in cases:
            with pytest.raises(ValueError, match=match), _note(mod, change):
                mod.warp_features(**{**base, **change})


class _note:
    """Names the failing case in the traceback."""

    def __init__(self, mod, change):
        self.what = f"{mod.__name__}: {sorted(change)}"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if exc[0] is not None and not issubclass(exc[0], ValueError):
            raise AssertionError(self.what) from exc[1]
        if exc[0] is None:
            raise AssertionError(f"{self.what} did not raise")
        return False


def test_support_mask(rt):
    """m^P_n: inside view n's mask, the pixels a valid point of P reaches."""
    scene = _scene(19, 1)
    _, wt, _ = warp.warp_features(*scene[:8], src_depth=scene[8])
    mask = torch.zeros(wt.shape, dtype=torch.bool)
    mask[:, : wt.shape[1] // 2] = True
    m = warp.support_mask(wt, mask)
    assert torch.equal(m, mask & (wt > 0))
    assert 0 < m.sum() < mask.sum()
    with pytest.raises(ValueError, match="shape"):
        warp.support_mask(wt, mask[1:])
