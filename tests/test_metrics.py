"""Metrics: agreement with scikit-image, masked variants by hand, the Frechet distance, VGG-PD's
algebra and known answers (blur, JPEG, noise, shift against PSNR; the real weights when installed)
(`coin-cl eval` over a folder: tests/test_evaluation.py; the LPIPS and Inception networks and their
weight loading: tests/test_nets.py; the VGG16 trunk's: tests/test_nets_vgg16_h5.py)."""

import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from coin_cl import metrics as M


def _pair(seed, H=40, W=48):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 1, (H, W, 3))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    return pred, gt


def test_psnr_ssim_equal_scikit_image():
    pred, gt = _pair(0)
    assert M.psnr(pred, gt) == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0))
    ref = structural_similarity(
        gt,
        pred,
        data_range=1.0,
        channel_axis=-1,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )
    assert M.ssim(pred, gt) == pytest.approx(ref)
    # scikit-image's mean leaves out the 5 px border the 11 px window cannot cover
    assert M.ssim_map(pred, gt)[5:-5, 5:-5].mean() == pytest.approx(ref, rel=1e-9)
    assert M.psnr(gt, gt) == math.inf and M.ssim(gt, gt) == pytest.approx(1.0)


def test_masked_psnr_by_hand():
    gt = np.zeros((2, 3, 3))
    pred = np.zeros((2, 3, 3))
    pred[0, 0] = 0.1  # inside the mask
    pred[1, 2] = 0.5  # outside: must not count
    mask = np.array([[True, True, False], [False, False, False]])
    # mse over 2 pixels x 3 channels = (3 * 0.01) / 6
    assert M.masked_psnr(pred, gt, mask) == pytest.approx(10 * np.log10(1 / 0.005))
    assert M.masked_psnr(pred, gt, ~mask) < M.masked_psnr(pred, gt, mask)
    assert math.isnan(M.masked_psnr(pred, gt, np.zeros((2, 3), bool)))
    assert M.masked_psnr(gt, gt, mask) == math.inf


def test_masked_ssim_is_map_mean_inside_mask():
    pred, gt = _pair(1)
    mask = np.zeros(gt.shape[:2], bool)
    mask[10:20, 5:30] = True
    pred2 = pred.copy()
    pred2[~mask] = gt[~mask]  # perfect outside the mask
    S = M.ssim_map(pred2, gt)
    assert M.masked_ssim(pred2, gt, mask) == pytest.approx(S[mask].mean())
    # far from the mask the map is exactly 1 and inside it is not
    assert np.allclose(S[35:, 40:], 1.0) and M.masked_ssim(pred2, gt, mask) < 0.99


def test_bbox_crop_by_hand():
    m = np.zeros((40, 50), bool)
    m[10:25, 20:40] = True
    m[12, 15] = True
    rows, cols = M.bbox_crop(m)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (10, 25, 15, 40)
    tiny = np.zeros((40, 50), bool)
    tiny[0, 49] = True  # a corner pixel grows to the 11 px SSIM window, clipped to the image
    rows, cols = M.bbox_crop(tiny)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (0, 11, 39, 50)
    assert M.bbox_crop(np.zeros((5, 5), bool)) is None
    pred, gt = _pair(2)
    mb = np.zeros(gt.shape[:2], bool)
    mb[5:30, 8:40] = True
    got = M.bbox_metrics(pred, gt, mb)
    assert got["bbox_psnr"] == pytest.approx(M.psnr(pred[5:30, 8:40], gt[5:30, 8:40]))
    assert got["bbox_ssim"] == pytest.approx(M.ssim(pred[5:30, 8:40], gt[5:30, 8:40]))


def test_aggregate_handles_inf_nan_none():
    views = [
        {"psnr": 20.0, "m_psnr": math.nan, "lpips": None},
        {"psnr": 30.0, "m_psnr": 10.0, "lpips": None},
    ]
    agg = M.aggregate(views)
    assert agg == {"psnr": 25.0, "m_psnr": 10.0, "lpips": None}
    assert M.aggregate([{"psnr": math.inf}, {"psnr": 20.0}])["psnr"] == math.inf
    assert M.jsonable({"a": [math.inf, math.nan, 1.0]}) == {"a": ["inf", "nan", 1.0]}


# ---------------------------------------------------------------- FID


def test_frechet_distance_by_hand():
    rng = np.random.default_rng(9)
    a = rng.normal(1.0, 2.0, (200, 1))
    b = rng.normal(-0.5, 0.5, (300, 1))
    # 1-D: (m1 - m2)^2 + (s1 - s2)^2 with the sample statistics
    want = (a.mean() - b.mean()) ** 2 + (a.std(ddof=1) - b.std(ddof=1)) ** 2
    assert M.frechet_distance(a, b) == pytest.approx(want, rel=1e-6)
    x = rng.normal(size=(50, 4)) @ rng.normal(size=(4, 4))
    y = rng.normal(size=(60, 4)) @ rng.normal(size=(4, 4)) + 0.3
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    w, V = np.linalg.eigh(s1)
    r1 = V @ np.diag(np.sqrt(w)) @ V.T  # tr sqrt(S1 S2) = tr sqrt(S1^1/2 S2 S1^1/2)
    tr = np.sqrt(np.clip(np.linalg.eigvalsh(r1 @ s2 @ r1), 0, None)).sum()
    d = x.mean(0) - y.mean(0)
    want = d @ d + np.trace(s1) + np.trace(s2) - 2 * tr
    assert M.frechet_distance(x, y) == pytest.approx(want, rel=1e-6)
    assert M.frechet_distance(x, x) == pytest.approx(0.0, abs=1e-6)
    # more samples than dimensions goes through scipy's sqrtm: same value
    big_x, big_y = np.repeat(x, 2, axis=0)[:9], y[:9]
    narrow = M.frechet_distance(big_x[:, :3], big_y[:, :3])
    s1, s2 = np.cov(big_x[:, :3], rowvar=False), np.cov(big_y[:, :3], rowvar=False)
    w, V = np.linalg.eigh(s1)
    r1 = V @ np.diag(np.sqrt(np.clip(w, 0, None))) @ V.T
    tr = np.sqrt(np.clip(np.linalg.eigvalsh(r1 @ s2 @ r1), 0, None)).sum()
    d = big_x[:, :3].mean(0) - big_y[:, :3].mean(0)
    assert narrow == pytest.approx(d @ d + np.trace(s1) + np.trace(s2) - 2 * tr, rel=1e-6)


def test_hf_ratio_and_gmsd_see_blur():
    rng = np.random.default_rng(3)
    gt = rng.random((64, 64, 3)).astype(np.float32)
    blur = cv2.GaussianBlur(gt, (0, 0), 2.0)
    mask = np.zeros((64, 64), bool)
    mask[16:48, 16:48] = True
    assert M.hf_ratio(gt, gt, mask) == pytest.approx(1.0)
    assert M.hf_ratio(blur, gt, mask) < 0.5  # a smear
    assert M.hf_ratio(gt, blur, mask) > 2.0  # stronger texture than the truth
    assert M.hf_ratio(blur, gt, mask, power=2) < M.hf_ratio(blur, gt, mask)
    assert math.isnan(M.hf_ratio(gt, gt, np.zeros((64, 64), bool)))
    flat = np.full((64, 64, 3), 0.5, np.float32)
    assert math.isnan(M.hf_ratio(gt, flat, mask))
    assert M.gmsd(gt, gt) == pytest.approx(0.0, abs=1e-9)
    assert M.bbox_gmsd(blur, gt, mask) > 0.05
    assert math.isnan(M.bbox_gmsd(gt, gt, np.zeros((64, 64), bool)))
    v = M.evaluate_view(blur, gt, mask)
    assert v["hf_ratio"] < 0.5 and v["bbox_gmsd"] > 0.05


def test_gmsd_is_on_luminance():
    """GMSD sees structure in any channel (on luminance, as Xue et al. define it; reading OpenCV's
    per-channel result at channel 0 saw the red channel alone): equal to the GMSD of the grey images,
    and the standard deviation of its half-resolution map."""
    rng = np.random.default_rng(5)
    gt = rng.random((48, 40, 3)).astype(np.float32)
    pred = gt.copy()
    pred[..., 1:] = cv2.GaussianBlur(np.ascontiguousarray(gt[..., 1:]), (0, 0), 2.0)  # red untouched
    assert M.gmsd(pred, gt) > 0.05

    def grey(x):
        return np.repeat(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY)[..., None], 3, axis=-1)

    assert M.gmsd(pred, gt) == pytest.approx(M.gmsd(grey(pred), grey(gt)), rel=1e-5)
    v, q = M.gmsd_map(pred, gt)
    assert q.shape == (24, 20) and v == pytest.approx(float(q.std()), rel=1e-4)
    assert M.gmsd_map(gt, gt)[1] == pytest.approx(np.ones((24, 20)))


def test_mask_texture_is_the_hf_ratio_terms():
    """mask_texture: 0 on a flat image, a known value on a ramp, NaN on an empty mask, a clear error
    on a mask of another size; hf_ratio is the ratio of two of them."""
    rng = np.random.default_rng(4)
    gt = rng.random((40, 50, 3)).astype(np.float32)
    pred = cv2.GaussianBlur(gt, (0, 0), 1.0)
    mask = np.zeros((40, 50), bool)
    mask[10:30, 5:45] = True
    assert M.mask_texture(np.full((40, 50, 3), 0.3, np.float32), mask) == 0.0
    ramp = np.repeat(np.tile(np.arange(50, dtype=np.float32) / 100, (40, 1))[..., None], 3, 2)
    assert M.mask_texture(ramp, mask) == pytest.approx(0.08, rel=1e-4)  # Sobel x: 8 x slope 0.01
    assert math.isnan(M.mask_texture(gt, np.zeros((40, 50), bool)))
    with pytest.raises(ValueError, match="does not match"):
        M.mask_texture(gt, np.ones((40, 49), bool))
    assert M.hf_ratio(pred, gt, mask) == pytest.approx(M.mask_texture(pred, mask) / M.mask_texture(gt, mask))


# ---- SWD and the colour check ----


def _texture(H=96, W=96, seed=0):
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.random((H, W, 3)).astype(np.float32), (0, 0), 1.0)
    return (g - g.min()) / (g.max() - g.min())


def _box_mask(H=96, W=96):
    m = np.zeros((H, W), bool)
    m[20:70, 24:74] = True
    return m


def test_swd_zero_identical_blur_worse_than_shift():
    g, m = _texture(), _box_mask()
    assert M.swd(g, g, m) == 0.0
    shifted = np.roll(g, 1, axis=1)
    blurred = cv2.GaussianBlur(g, (0, 0), 2.0)
    s_shift, s_blur = M.swd(shifted, g, m), M.swd(blurred, g, m)
    assert 0 < s_shift < s_blur / 5
    assert M.swd(g, g, np.zeros_like(m)) != M.swd(g, g, np.zeros_like(m))  # NaN for an empty mask
    assert M.swd(shifted, g, None) == pytest.approx(M.swd(shifted, g, None))  # deterministic


def test_color_distance_hue_noise_worse_than_shift():
    g, m = _texture(), _box_mask()
    assert M.color_distance(g, g, m) == 0.0
    hsv = cv2.cvtColor(g, cv2.COLOR_RGB2HSV)
    rng = np.random.default_rng(1)
    hsv[..., 0] = (hsv[..., 0] + rng.normal(0, 60, hsv.shape[:2])) % 360
    hsv[..., 1] = np.maximum(hsv[..., 1], 0.5)
    noisy = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    c_shift, c_noise = M.color_distance(np.roll(g, 1, axis=1), g, m), M.color_distance(noisy, g, m)
    assert c_shift < c_noise / 10
    assert math.isnan(M.color_distance(g, g, np.zeros_like(m)))


def test_evaluate_view_has_swd_and_colour():
    g, m = _texture(), _box_mask()
    d = M.evaluate_view(np.roll(g, 1, axis=1), g, m)
    assert d["swd"] > 0 and d["color_dist"] >= 0
    d0 = M.evaluate_view(g, g, None)
    assert math.isnan(d0["swd"]) and math.isnan(d0["color_dist"])


# ---------------------------------------------------------------- VGG-PD (coin_cl.nets.vgg16_h5)

# The shared data beside the repository, or $COIN_DATA (as tests/conftest.py's shared_data_dir)
CUP = (
    Path(os.environ.get("COIN_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
    / "cup_capture"
    / "images"
    / "1.jpg"
)


@pytest.fixture(scope="module")
def random_trunk():
    """A VGG16 trunk with seeded random weights: for the distance's algebra only (zero, symmetry,
    masks), never for its values."""
    from coin_cl.nets.vgg16_h5 import VGG16Trunk

    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    return VGG16Trunk().eval().requires_grad_(False)


@pytest.fixture(scope="module")
def vgg():
    from coin_cl.nets.vgg16_h5 import vgg16_h5_from_env

    model, reason = vgg16_h5_from_env()
    if model is None:
        pytest.skip(reason)
    return model


def procedural_image(size=112, seed=0):
    """A natural-looking (H, W, 3) [0, 1] image: 1/f (pink) noise with correlated colour under a
    few sharp-edged discs and bars."""
    rng = np.random.default_rng(seed)
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(size), np.fft.fftfreq(size)))
    f[0, 0] = 1
    base = np.stack(
        [np.fft.ifft2(np.fft.fft2(rng.standard_normal((size, size))) / f).real for _ in range(3)], -1
    )
    base = base @ np.array([[1, 0.8, 0.6], [0.2, 1, 0.3], [0.1, 0.2, 1]])
    img = 0.5 + 0.15 * (base - base.mean()) / base.std()
    yy, xx = np.mgrid[:size, :size]
    for _ in range(6):
        cy, cx, r = rng.uniform(0, size, 2).tolist() + [rng.uniform(6, 20)]
        img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.uniform(0.1, 0.9, 3)
    for _ in range(3):
        x0 = int(rng.integers(0, size - 10))
        img[:, x0 : x0 + int(rng.integers(3, 10))] = rng.uniform(0.1, 0.9, 3)
    return np.clip(img, 0, 1).astype(np.float32)


def source_image(kind):
    """(the 112 x 112 source, the 96 x 96 crop at (8, 8)): crops of a larger image so that blurs
    and shifts see real pixels at the borders."""
    if kind == "real":
        if not CUP.is_file():
            pytest.skip(f"{CUP} absent (the cup capture: research data, not shipped; set COIN_DATA)")
        # the gold lettering on the cup: fine edges, where a 1-px shift costs PSNR more than a blur
        img = cv2.imread(str(CUP))[246:358, 534:646, ::-1].astype(np.float32) / 255
    else:
        img = procedural_image()
    return img, img[8:104, 8:104]


def jpeg(img, quality):
    ok, buf = cv2.imencode(
        ".jpg", (img[..., ::-1] * 255).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255


def distances(model, distorted, ref):
    """VGG-PD of each distorted image against ref, in one batch."""
    import torch

    a = torch.as_tensor(np.stack(distorted)).permute(0, 3, 1, 2)
    b = torch.as_tensor(ref).permute(2, 0, 1)[None]  # one reference for the whole batch
    with torch.no_grad():
        return M.vgg_pd_torch(model, a, b).numpy()


def test_vgg_pd_algebra(random_trunk):
    img = procedural_image(64)
    other = np.clip(img + 0.1 * np.random.default_rng(1).standard_normal(img.shape), 0, 1).astype(np.float32)
    assert M.vgg_pd(random_trunk, img, img) == 0.0
    d = M.vgg_pd(random_trunk, other, img)
    assert 0 < d <= 10 and d == pytest.approx(M.vgg_pd(random_trunk, img, other), rel=1e-5)
    full = np.ones(img.shape[:2], bool)
    assert M.bbox_vgg_pd(random_trunk, other, img, full) == d  # the full mask's box is the image
    assert math.isnan(M.bbox_vgg_pd(random_trunk, other, img, ~full))
    part = np.zeros(img.shape[:2], bool)
    part[10:50, 20:60] = True
    assert M.bbox_vgg_pd(random_trunk, other, img, part) == M.vgg_pd(
        random_trunk, other[10:50, 20:60], img[10:50, 20:60]
    )
    with pytest.raises(ValueError, match="at least 32 px"):
        M.vgg_pd(random_trunk, img[:20], img[:20])
    bad = img.copy()
    bad[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        M.vgg_pd(random_trunk, bad, img)
    out = M.evaluate_view(other, img, part, vgg_model=random_trunk)
    assert out["vgg_pd"] == d and out["m_vgg_pd"] > 0
    assert M.evaluate_view(other, img, part)["vgg_pd"] is None
    tiny = M.evaluate_view(other[:20, :24], img[:20, :24], part[:20, :24], vgg_model=random_trunk)
    assert math.isnan(tiny["vgg_pd"]) and math.isnan(tiny["m_vgg_pd"])  # under 32 px: none, not an error


@pytest.mark.parametrize("kind", ["real", "procedural"])
def test_vgg_pd_grows_with_blur_jpeg_and_noise(vgg, kind):
    src, ref = source_image(kind)
    crop = lambda x: x[8:104, 8:104]  # noqa: E731
    noise = np.random.default_rng(0).standard_normal(src.shape).astype(np.float32)
    series = {
        "blur": [crop(cv2.GaussianBlur(src, (0, 0), s)) for s in (1, 2, 4)],
        "jpeg": [jpeg(ref, q) for q in (90, 50, 10)],
        "noise": [crop(np.clip(src + s * noise, 0, 1)) for s in (0.02, 0.05, 0.1)],
    }
    d = distances(vgg, [ref] + [x for v in series.values() for x in v], ref)
    assert d[0] < 1e-9  # the reference itself (batched convolutions differ from single ones by ~1e-12)
    for i, (name, _) in enumerate(series.items()):
        vals = d[1 + 3 * i : 4 + 3 * i]
        assert np.all(np.diff(vals) > 0) and vals[0] > 0, (name, vals)


@pytest.mark.parametrize("kind", ["real", "procedural"])
def test_vgg_pd_judges_a_shift_closer_than_a_blur_unlike_psnr(vgg, kind):
    src, ref = source_image(kind)
    shifted = src[8:104, 9:105]  # the view moved by one pixel
    blurred = cv2.GaussianBlur(src, (0, 0), 2)[8:104, 8:104]
    d_shift, d_blur = distances(vgg, [shifted, blurred], ref)
    assert d_shift < d_blur
    assert M.psnr(shifted, ref) < M.psnr(blurred, ref)  # PSNR prefers the blur on the same pair


def _ghost_scene(bump: float = 0.5):
    """A plane at depth 4 seen head-on, a 20x20 mask in a 64x64 view, and a render that leaves a
    6x20 slab of the object at `bump` of the surface's depth inside the mask."""
    ref = np.full((64, 64), 4.0)
    mask = np.zeros((64, 64), bool)
    mask[22:42, 22:42] = True
    render = ref.copy()
    render[22:28, 22:42] = bump * 4.0
    return render, ref, mask


def test_ghost_is_the_share_of_the_mask_in_front_of_the_reference():
    render, ref, mask = _ghost_scene()
    assert M.ghost_fraction(render, ref, mask) == pytest.approx(120 / 400)
    assert M.ghost_fraction(ref, ref, mask) == 0.0
    render[22:24, 22:42] = np.inf  # nothing drawn there: no ghost
    assert M.ghost_fraction(render, ref, mask) == pytest.approx(80 / 400)
    assert math.isnan(M.ghost_fraction(render, ref, np.zeros_like(mask)))


def test_ring_relative_ghost_ignores_a_reference_that_disagrees_everywhere_alike():
    render, ref, mask = _ghost_scene()
    far_ref = ref / 0.85  # a reference fitted apart, 15 % deeper than the render around the mask too
    assert M.ghost_fraction(render, far_ref, mask) == 1.0  # the plain figure counts the disagreement
    assert M.ghost_fraction(render, far_ref, mask, ring=(3, 15)) == pytest.approx(120 / 400)
    assert M.ghost_fraction(ref, far_ref, mask, ring=(3, 15)) == 0.0


def test_ghost_counted_on_a_region_outside_the_mask_is_the_floor():
    render, ref, mask = _ghost_scene()
    outside = np.zeros_like(mask)
    outside[50:60, 10:54] = True  # a band where nothing was removed
    assert M.ghost_fraction(render, ref, mask, ring=(3, 15), region=outside) == 0.0
    noisy = render.copy()
    noisy[50:55, 10:54] = 0.8 * ref[50:55, 10:54]  # the surface itself 20 % in front there
    assert M.ghost_fraction(noisy, ref, mask, ring=(3, 15), region=outside) == pytest.approx(0.5)
    assert M.ghost_fraction(noisy, ref, mask, ring=(3, 15)) == pytest.approx(120 / 400)  # the mask's
    with pytest.raises(ValueError, match="region"):
        M.ghost_fraction(render, ref, mask, region=outside[:10])


def test_ring_relative_ghost_without_a_ring_is_nan_and_a_bad_ring_an_error():
    render, ref, mask = _ghost_scene()
    render[:] = np.nan  # nothing rendered anywhere: no ring to calibrate against
    assert math.isnan(M.ghost_fraction(render, ref, mask, ring=(3, 15)))
    with pytest.raises(ValueError, match="ring"):
        M.ghost_fraction(ref, ref, mask, ring=(5, 5))
