"""The detail band of CLG's output (CoIn paper 4.3): the guided sample lives at the sampler's
working size (64 px for the scene prior, 512 for SD2), while the hole's crop is often several times
larger, so a sample brought back to the crop has no detail above the working resolution, and the
guard (`coin_cl.pipeline.clg_guard.no_worse`) then keeps the blurrier input in most views.

A Laplacian split fixes that: with down = area resize to a side of `split` x work and up = bicubic
resize back to the crop (how the sample itself is brought back),

    low(I) = up(down(I)),   high(I) = I - low(I),
    output = low(up(x)) + high(D)

where x is the guided sample (the band the energy can steer) and D the detail source, by
`CLGConfig.detail`:
- "input": the initial inpaint I^_n everywhere (its texture above the split is kept unchanged; where
  the sample's low band equals I^_n's the output is I^_n);
- "reference" (default): the reference's detail warped through P_k (`reprojection.reference_in_view`
  of high(I^_k), the split made at view n's scale) on the pixels the warp supports, I^_n's elsewhere:
  the guidance pulls the low band toward the reference, and the detail there comes from the same
  reference through the same geometry, so the residual to the reference falls in both bands;
- "none": up(x) alone (no detail band: the paper's paste of the sample).
`CLGConfig.detail_split` (default 0.5) sets the split; at 1 it is the working resolution itself,
where the 64 px sample still carries its own noise-like texture into the output (measured: the
shared scene's images were then further from the reference than the inputs).

The colours of the low band (`CLGConfig.colour_match`, on by default): the scene prior's 64 px
sample follows the reference's structure but not its colours: on the shared scene its images were
closer to the reference than the LaMa inputs (residual 0.077 -> 0.053) while their hues drifted
(a purple cast and 64 px chroma blotches; the Lab distance to the mask's surroundings doubled), so
the guard kept the input in every view. `match_colour` moves the low band's Lab mean and standard
deviation inside the hole to those of the energy's own target (`colour_target`: the reference warped
through P_k where supported, I^_n elsewhere) taken to the same band; the gain on the deviation is
capped at 1, so the match can damp the sample's blotches but never amplifies what it drew.

Chroma from the target (`CLGConfig.chroma_from_target`, on by default): a global match still left
64 px hue blotches (pink and green over the bench and the bush in the accepted views of the shared
scene), so the low band's chroma (Lab a, b) inside the hole is the target's low band's, pixel by
pixel, and the sample steers the lightness alone. On the shared scene's LaMa inpaints
(benchmarks/clg.py) the same views pass, their residual to the reference falls further (0.0692 ->
0.0675) and the blotches are gone from the crop grid (docs/RESULTS.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from coin_cl.crop import crop_image, resize_to
from coin_cl.pipeline.clg_config import DETAILS
from coin_cl.pipeline.reprojection import reference_in_view

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Camera


@dataclass
class ReferenceView:
    """The reference view as every view's CLG sees it (what `reference_warp` warps from)."""

    k: int
    cam: Camera
    image: np.ndarray  # [Hk, Wk, 3] I^_k
    depth: np.ndarray | None  # [Hk, Wk] rendered camera z or None
    points: np.ndarray  # [M, 3] P_k
    mask: np.ndarray | None = None  # [Hk, Wk] bool its mask (the lifted residual's target region)


def high_band(img: np.ndarray, w_low: int, h_low: int) -> np.ndarray:
    """(H, W, C) float -> (H, W, C): img minus img taken down to (w_low, h_low) (area) and back up
    (bicubic). Zero when the low size is the image's own."""
    H, W = img.shape[:2]
    w_low, h_low = max(1, int(w_low)), max(1, int(h_low))
    if (w_low, h_low) == (W, H):
        return np.zeros_like(img)
    low = resize_to(resize_to(img, w_low, h_low), W, H)
    return (img - low).astype(np.float32)


def reference_warp(
    ref: ReferenceView, cam_n: Camera, device: DeviceLike, detail_scale: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The reference image warped into view n through P_k in one pass, with its high band (split at
    `detail_scale` x its size: view n's working scale) as three more channels when a scale is given:
    ((H, W, 3 or 6), (H, W) weights, 0 where no point lands). One warp serves the colour target, the
    detail band and every residual of the view (the geometry is the same; the warp is linear in the
    values it carries)."""
    img = ref.image[..., :3]
    if detail_scale is not None:
        Hk, Wk = img.shape[:2]
        img = np.concatenate([img, high_band(img, round(Wk * detail_scale), round(Hk * detail_scale))], -1)
    return reference_in_view(img, cam_n, ref.cam, ref.points, ref.depth, device)


def reference_detail(warp: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The reference's high band in view n from `reference_warp(..., detail_scale)`: ((H, W, 3)
    detail, (H, W) bool where the warp supports it)."""
    warped, weight = warp
    return warped[..., 3:6], weight > 0


def colour_target(warp: tuple[np.ndarray, np.ndarray], inp_n: np.ndarray) -> np.ndarray:
    """(H, W, 3): what CLG's RGB term pulls view n toward: the reference image warped through P_k
    (`reference_warp`) where the warp lands, the initial inpaint I^_n `inp_n` elsewhere."""
    warped, weight = warp
    return np.where((weight > 0)[..., None], warped[..., :3], inp_n).astype(np.float32)


def match_colour(
    img: np.ndarray, target: np.ndarray, region: np.ndarray, max_gain: float = 1.0, chroma: bool = False
) -> np.ndarray:
    """(H, W, 3) float RGB -> (H, W, 3): `img` with its Lab mean and standard deviation per channel
    inside `region` (H, W) bool moved to `target`'s there: lab' = mean_t + g (lab - mean_i), with
    g = min(std_t / std_i, max_gain) (a flat img is only shifted). chroma: inside the region the
    chroma (a, b) is `target`'s own, pixel by pixel, and only the lightness is matched. Values
    outside [0, 1] are clipped for the conversion. `img` unchanged when the region is empty."""
    import cv2

    region = np.asarray(region, bool)
    if not region.any():
        return img
    lab = cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)
    lab_t = cv2.cvtColor(np.clip(target, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)
    a, b = lab[region], lab_t[region]
    mu_a, mu_b, sd_a, sd_b = a.mean(0), b.mean(0), a.std(0), b.std(0)
    gain = np.minimum(sd_b / np.maximum(sd_a, 1e-6), max_gain)
    lab_o = mu_b + gain * (lab - mu_a)
    if chroma:
        lab_o[..., 1:] = np.where(region[..., None], lab_t[..., 1:], lab_o[..., 1:])
    out = cv2.cvtColor(lab_o.astype(np.float32), cv2.COLOR_LAB2RGB)
    return out.astype(np.float32)


def crop_bands(
    fill: np.ndarray,
    inp_n: np.ndarray,
    y0: int,
    x0: int,
    side: int,
    detail: str,
    ref_detail: tuple[np.ndarray, np.ndarray] | None = None,
    split: float = 1.0,
    colour: tuple[np.ndarray, np.ndarray] | None = None,
    chroma: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The two bands of the crop [side, side, 3] CLG pastes, (low, high): the sample `fill`
    [work, work, 3] brought back to the crop at (y0, x0) of view n, its band below `split` x work,
    and the high band of the detail source (module docstring; zero for detail "none", whose low band
    is the whole upsampled sample). ref_detail: `reference_detail`'s pair (split at the same scale),
    required for detail "reference". colour: (target [H, W, 3], hole [H, W] bool) of view n: the
    low band's colours are matched to the target's low band inside the hole (`match_colour`; with
    `chroma` its chroma is the target's low band's, only its lightness is the sample's); not used
    by detail "none". Split from `compose_crop` so the top-up (`texture_gain`) rescales the high
    band without recomputing either."""
    if detail not in DETAILS:
        raise ValueError(f"CLGConfig.detail must be one of {', '.join(DETAILS)}, got {detail!r}")
    work = fill.shape[0]
    low = max(1, round(work * split))
    if detail == "none":
        up = resize_to(fill, side, side)
        return up, np.zeros_like(up)
    back = resize_to(resize_to(fill, low, low), side, side)  # the sample's band below the split
    if colour is not None:
        target, hole = (crop_image(a, y0, x0, side, side) for a in colour)
        back = match_colour(back, resize_to(resize_to(target, low, low), side, side), hole, chroma=chroma)
    hi = high_band(crop_image(inp_n, y0, x0, side, side), low, low)
    if detail == "reference":
        if ref_detail is None:
            raise ValueError("detail 'reference' needs the reference's warped detail")
        warped, sup = ref_detail
        sup_c = crop_image(sup, y0, x0, side, side)
        hi = np.where(sup_c[..., None], crop_image(warped, y0, x0, side, side), hi)
    return back, hi


def compose_crop(*args: Any, detail_gain: float = 1.0, **kwargs: Any) -> np.ndarray:
    """The crop [side, side, 3] CLG pastes: low + detail_gain x high of `crop_bands` (same
    arguments, forwarded as given); detail_gain is the top-up's gain on the high band
    (`texture_gain` picks it)."""
    back, hi = crop_bands(*args, **kwargs)
    return (back + detail_gain * hi).astype(np.float32)


def texture_gain(
    compose: Callable[[float], np.ndarray],
    texture: Callable[[np.ndarray], float],
    target: float,
    max_gain: float,
    iters: int = 8,
) -> tuple[np.ndarray, float]:
    """The detail band's top-up (`CLGConfig.detail_gain_max`): (output, gain) with the smallest gain
    in [1, max_gain] (bisection, `iters` halvings) at which `texture(compose(gain))` reaches
    `target`, or max_gain when even that falls short. compose(gain) -> (H, W, 3): the view's output
    with its high band times gain. Gain 1 (the output unchanged) when that already reaches the
    target, the target is not finite or max_gain <= 1."""
    out = compose(1.0)
    if not np.isfinite(target) or max_gain <= 1.0 or texture(out) >= target:
        return out, 1.0
    top = compose(max_gain)
    if texture(top) < target:
        return top, float(max_gain)
    lo, hi, best = 1.0, float(max_gain), top
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        cand = compose(mid)
        if texture(cand) >= target:
            hi, best = mid, cand
        else:
            lo = mid
    return best, hi
