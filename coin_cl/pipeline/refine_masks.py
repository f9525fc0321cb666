"""3D-first refined masks (paper supplement C.2) for 360-degree and other wide captures: stage
`0_refine`, run before stage 1 when `CoInConfig.inpaint_region == "refined"`
(`coin-cl run --inpaint-region refined`).

A 2D-first pipeline inpaints the whole object mask in every view, although a wide capture sees most
of what the object hides from some other view. Here:

1. a GS (`RefineConfig.model`, `iters` steps) is fitted to the captured training views, object and all;
2. its Gaussians are exported (`export_gaussians`; a Scaffold model is decoded at the mean camera
   centre) and those whose centre projects inside the mask in at least `min_fraction` of the
   training views that see it are removed (`prune_points_in_masks`' vote: the object is inside the
   mask from every view, background behind it only from some), leaving G^rmv. The vote is
   unanimous by default: background just behind the object lies inside the masks of most views,
   and a point that a single view sees outside its mask is background (a majority vote deleted it,
   and the split then inpainted what that view saw; measured below). It relies on the masks
   covering the object's fringe in every view, which the pipeline's default dilation does
   (`CoInConfig.mask_dilate`); on masks dilated less than that ring (`--mask-dilate 0`) the vote
   takes them widened to it (`vote_ring`), the loss and the split keep them as given;
3. G^rmv is rendered with fixed scales: every Gaussian an isotropic disk of `splat_px` pixels
   (its world radius set from its camera z in that view, so near and far surfaces are judged
   alike), so that coverage means a surface point nearby, not one large Gaussian smeared over the
   hole; the refined mask M^rmv_n (the unseen core) is the input mask where that alpha is below
   `alpha_thresh`, plus the covered pixels whose rendered depth lies more than `see_through` beyond
   the surroundings' depth carried inward (the removal exposed what is behind a surface nobody
   saw, e.g. the floor under the table under the object), grown by `grow_px` pixels inside the
   input mask, plus the observed islands: parts of at most `island_px` pixels, and parts enclosed
   by the unseen core (`enclosed`: touching no pixel outside the mask). With `view_check` (off by
   default) a covered pixel is observed instead only when its rendered surface point is seen by
   another training view outside that view's mask, at the depth that view renders, and every
   point of the ray in front of it is known empty (`seen_elsewhere`);
   a view whose render of G^rmv reproduces its capture around the mask no better than one flat
   colour keeps no observed part: its whole input mask is its unseen core (`fit_check`);
4. R^rmv_n, the render of G^rmv with its own scales, stands in for the captured pixels in the input
   mask outside M^rmv_n.

Measured (demo room: 90-degree arc, 192x144, 18 training views, a 591-step fit,
against the ray-cast visibility `coin_cl.scene.synthetic.truly_unseen`). The default rule marks
20.1 % of the exactly observed mask pixels unseen (unseen core: precision 0.59, recall 0.96): 11.7
points from the see-through test (the depth carried inward from the mask's border is too shallow
where the mask spans a depth edge, the table top in front and the wall behind), 6.5 from the
growth, 1.9 from coverage (coverage alone: recall 0.46). The view check marks 10.7 % (precision
0.72, recall 0.92; without the ray test 6.5 % but recall 0.73). Yet end to end (CoIn at the demo's
steps, docs/RESULTS.md) the view check scored 0.63 dB m-PSNR lower (21.46 against 22.09), on the
observed part of the test masks too (25.49 against 25.84; single runs). Why, measured later
(`benchmarks/refine_split.py`, docs/RESULTS.md "Why the split inpaints what other views saw"): the
pixels the see-through rule and the growth took from the observed part were where R^rmv_n was
wrong (scored on the pixels each rule marks observed: 27.1 dB under that rule, 25.5 under the view
check, 21.6 with neither), because the majority vote then used in step 2 deleted the background
just behind the object, and G^rmv showed a hole there. With the unanimous vote and no growth (the
defaults since): precision 0.46 -> 0.75 at recall 0.96 -> 0.94, observed share 0.52 -> 0.71 (exact
0.77), the observed target 27.1 -> 26.3 dB on that larger part; end to end (single runs) the
360-degree room gains m-PSNR 21.89 -> 21.96, HF ratio 0.77 -> 0.83, bbox GMSD 0.169 -> 0.159,
and the demo room 21.45 -> 21.87 (HF 0.76 -> 0.73, GMSD 0.179 -> 0.181). A 0.9 vote (17 of 18
views) cost the 360-degree room 0.65 dB instead; why one view's vote matters that much there is
not isolated.

The later stages then inpaint M^rmv_n only, with R^rmv_n outside it in the mask. Files (stage folder):
masks/<stem>.png (M^rmv_n), images/<stem>.png (the capture, R^rmv_n in the input mask),
renders/<stem>.png (R^rmv_n), observed/<stem>.png and unseen/<stem>.png (the split of the input
mask, also for the test views given as `also`), areas.json (per training view: input and refined
mask pixels), gs/ (the fit).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import torch

from coin_cl.pipeline.observed_warp import warp_observed
from coin_cl.scene.io import to_uint8, write_png, write_text

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Camera, Scene

log = logging.getLogger(__name__)

# Per view: (R^rmv_n (H, W, 3), fixed-scale alpha (H, W), G^rmv's expected depth (H, W), the
# captured surface's depth (H, W), 0 where none); `fit_renders`.
Renders = dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


@dataclass
class RefineConfig:
    """Stage 0_refine's settings (module doc); each field says what it means where it is declared.
    Values are checked here: a bad one is an error naming the field."""

    # Steps of the object-present fit (>= 1). None (default): the run's Ref-GS step count.
    iters: int | None = None
    # The fit's model: "3dgs" (default) or "scaffold".
    model: str = "3dgs"
    # Removal vote (step 2), in (0, 1]: 1.0 (default) = inside the masks of every view that sees it.
    min_fraction: float = 1.0
    # The fixed render scale in pixels (step 3, > 0; about the spacing of a fitted GS's Gaussians on
    # a surface).
    splat_px: float = 1.5
    # Coverage below which a mask pixel is unseen, in [0, 1].
    alpha_thresh: float = 0.5
    # Dilation of M^rmv_n inside the input mask, px (>= 0).
    grow_px: int = 0
    # A covered pixel whose rendered depth exceeds the surroundings' (inpainted inward) by more than
    # this fraction is unseen too (>= 0; 0: off).
    see_through: float = 0.15
    # (>= 0; 0: off, the default) a covered mask pixel is observed only where its rendered surface
    # point is seen by another training view outside that view's mask, its camera z within this
    # fraction of the depth that view renders there, with `ray_samples` points of the ray in front of
    # it known empty (`seen_elsewhere`); the precise split of the module doc (0.05, with see_through 0
    # and grow_px 0), not the default because end to end it scored lower (module doc).
    view_check: float = 0.0
    # Points of the ray checked by view_check (>= 1).
    ray_samples: int = 24
    # (>= 0; 0: off, the default) a mask pixel whose object-free surface point another training view
    # captured (its depth there within this fraction, outside its mask) is observed, whatever the
    # rules above say, and takes that view's captured colour instead of R^rmv_n (`observed_warp`;
    # 0.03 measured, module doc).
    warp_tol: float = 0.0
    # (pixels, >= 0; 0: off) observed parts of the mask of at most this many pixels go back to the
    # unseen core (`fill_islands`). Their colours are R^rmv_n where its own coverage is thin,
    # composited over black, and stage 1 spreads such pinholes into dark fills: a virtual box on the
    # cup capture (docs/VIRTUAL_OBJECTS.md, cup_plain) had 221 such islands (1,878 px, 63% near-black)
    # and 16% of its unseen pixels dark (V < 60) after a Telea fill; with them in the hole, 2%.
    island_px: int = 20
    # Observed parts of the mask that touch no pixel outside it (enclosed by the unseen core and the
    # image border) go back to the unseen core too, whatever their size (`enclosed_parts`). A
    # background nobody saw all around cannot be trusted in its middle: on the cup_plain scene
    # (docs/VIRTUAL_OBJECTS.md) 76% of such pixels in the test views were more than 0.12 off the
    # truth (against 22% of all observed pixels), and 71% of them in the training views near-black
    # (the box's dark Gaussians that one view saw outside its mask), which stage 1 spread into dark
    # fills. False: off.
    enclosed: bool = True
    # A view's observed part is taken from R^rmv_n only where the fit shows it can reproduce that
    # view: around the mask (a ring of `fit_ring_px`), its render must be closer to the capture (mean
    # absolute RGB) than the ring's own median colour is; a fit that does no better than one flat
    # colour there carries nothing a 2D fill would not, and the whole input mask is that view's
    # unseen core (`fit_reproduces`). On the cup_plain scene (docs/VIRTUAL_OBJECTS.md; a 302-step
    # fit) the ring's error ranked the views' observed-part error against the untouched photos
    # (correlation 0.87): the 21 of 56 views it rejects had observed parts 0.111 off the truth, where
    # a whole-mask fill was 0.029 off; CoIn at the same steps then scored m-PSNR +0.15 dB and a 7.0%
    # lower masked VGG distance, GMSD 3.5% higher (one seed; docs/BENCHMARKS.md, "The split's fit,
    # checked around the mask"). False: off (every view keeps what the split calls observed).
    fit_check: bool = True
    # The ring's width in pixels (>= 1) at the working resolution.
    fit_ring_px: int = 8

    def __post_init__(self) -> None:
        if not (math.isfinite(self.warp_tol) and self.warp_tol >= 0):
            raise ValueError(f"RefineConfig.warp_tol must be finite and >= 0 (0: off), got {self.warp_tol}")
        for name, ok, what in (
            (
                "iters",
                self.iters is None or (isinstance(self.iters, int) and self.iters >= 1),
                ">= 1 or None",
            ),
            ("model", self.model in ("3dgs", "scaffold"), "'3dgs' or 'scaffold'"),
            ("min_fraction", 0.0 < self.min_fraction <= 1.0, "in (0, 1]"),
            ("splat_px", self.splat_px > 0, "> 0"),
            ("alpha_thresh", 0.0 <= self.alpha_thresh <= 1.0, "in [0, 1]"),
            ("grow_px", isinstance(self.grow_px, int) and self.grow_px >= 0, "an integer >= 0"),
            ("see_through", self.see_through >= 0, ">= 0"),
            ("view_check", self.view_check >= 0, ">= 0"),
            ("ray_samples", isinstance(self.ray_samples, int) and self.ray_samples >= 1, "an integer >= 1"),
            ("enclosed", isinstance(self.enclosed, bool), "True or False"),
            ("fit_check", isinstance(self.fit_check, bool), "True or False"),
            ("fit_ring_px", isinstance(self.fit_ring_px, int) and self.fit_ring_px >= 1, "an integer >= 1"),
            (
                "island_px",
                isinstance(self.island_px, int) and self.island_px >= 0,
                "an integer >= 0 (0: off)",
            ),
        ):
            if not ok:
                raise ValueError(f"RefineConfig.{name} is {getattr(self, name)!r}: give {what}")


def refine_masks(
    scene: Scene,
    masks: list[np.ndarray],
    train: list[int],
    out_dir: Path,
    cfg: RefineConfig,
    iters: int,
    seed: int = 0,
    device: DeviceLike = None,
    also: list[int] | tuple[int, ...] = (),
    vote_masks: list[np.ndarray] | None = None,
) -> dict[str, Any]:
    """Steps 1-4 of the module doc for the training views `train` of `scene` with input `masks`
    (per view (H, W) bool); writes the stage files into `out_dir`. vote_masks: the masks step 2's
    removal vote uses (default `masks`; wider ones where the input masks are tight, see
    `vote_ring`). `iters` is used when
    `cfg.iters` is None. Returns JSON-able figures: per-view areas and the refined / input ratio.
    A view with an empty input mask keeps an empty refined mask. `also`: further views (the
    object-absent test views) whose masks are split the same way, against the training views, into
    observed/ and unseen/ only (for the evaluation's grids and per-part scores)."""
    from coin_cl.scene.masks import write_mask

    out_dir = Path(out_dir)
    n_iters = int(cfg.iters if cfg.iters is not None else iters)
    renders, n_gauss, n_removed = fit_renders(
        scene, masks, train, out_dir / "gs", cfg, n_iters, seed, device, also, vote_masks
    )
    cams = {i: scene.cameras[i] for i in train}
    areas, unfit = {}, []
    for i in list(train) + list(also):
        stem = Path(scene.cameras[i].name).stem
        mask = np.asarray(masks[i], bool)
        trusted = fit_trusted(scene, renders, i, mask, cfg)
        refined, warped, found = split_view(scene, masks, renders, i, train, cfg, trusted)
        if not trusted and i in cams:
            unfit.append(stem)
        render = renders[i][0]
        write_mask(out_dir / "observed" / f"{stem}.png", mask & ~refined)
        write_mask(out_dir / "unseen" / f"{stem}.png", refined)
        if i not in cams:
            continue
        target = render if warped is None else np.where(found[..., None], warped, render)
        base = np.where((mask & ~refined)[..., None], target, scene.images[i]).astype(np.float32)
        write_png(out_dir / "renders" / f"{stem}.png", to_uint8(render))
        write_png(out_dir / "images" / f"{stem}.png", to_uint8(base))
        write_mask(out_dir / "masks" / f"{stem}.png", refined)
        areas[stem] = {"input_px": int(mask.sum()), "refined_px": int(refined.sum())}
        log.info("refine masks: view %s: %d -> %d px (%.0f%%)", stem, mask.sum(), refined.sum(),
                 100 * refined.sum() / max(1, mask.sum()))  # fmt: skip
    if unfit:
        log.info("refine masks: %d of %d training views keep no observed part: around their masks the "
                 "fit reproduces the capture no better than one flat colour (RefineConfig.fit_check): %s",
                 len(unfit), len(areas), ", ".join(unfit))  # fmt: skip
    write_text(out_dir / "areas.json", json.dumps(areas, indent=1, sort_keys=True))
    tot_in = sum(a["input_px"] for a in areas.values())
    tot_ref = sum(a["refined_px"] for a in areas.values())
    return {
        "iters": n_iters,
        "model": cfg.model,
        "n_gaussians": n_gauss,
        "n_removed": n_removed,
        "splat_px": cfg.splat_px,
        "input_px": tot_in,
        "refined_px": tot_ref,
        # refined over input mask area over all training views (1 = nothing gained; 0 with empty masks)
        "refined_ratio": tot_ref / tot_in if tot_in else 0.0,
        "areas": areas,
        # training views whose observed part was given up by the fit check (`RefineConfig.fit_check`)
        "fit_rejected": unfit,
    }


def fill_islands(unseen: np.ndarray, mask: np.ndarray, max_px: int) -> np.ndarray:
    """`unseen` (H, W) bool with every observed part of `mask` (H, W) bool (a 4-connected component of
    mask & ~unseen) of at most `max_px` pixels added; larger observed parts and everything outside
    the mask are unchanged."""
    observed = (mask & ~unseen).astype(np.uint8)
    if max_px <= 0 or not observed.any():
        return unseen
    n, labels, stats, _ = cv2.connectedComponentsWithStats(observed, connectivity=4)
    small = np.zeros(n, bool)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= max_px
    return unseen | small[labels]


def enclosed_parts(observed: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The pixels of `observed` (H, W) bool, a part of `mask` (H, W) bool, in 4-connected components
    that touch no pixel outside `mask` (8-neighbourhood; the image border is not outside): observed
    islands enclosed by the rest of the mask. (H, W) bool."""
    if not observed.any():
        return np.zeros_like(observed)
    n, labels = cv2.connectedComponents(observed.astype(np.uint8), connectivity=4)
    # border value 0: beyond the frame counts as neither outside nor observed
    near_outside = cv2.dilate((~mask).astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    touching = np.zeros(n, bool)
    touching[np.unique(labels[near_outside & observed])] = True
    touching[0] = True  # label 0 is everything not observed
    return ~touching[labels]


def fit_reproduces(render: np.ndarray, image: np.ndarray, mask: np.ndarray, ring_px: int) -> bool:
    """Whether `render` (H, W, 3) reproduces `image` (H, W, 3) around `mask` (H, W) bool better than
    one flat colour: over the ring of `ring_px` pixels outside the mask (8-neighbourhood, clipped
    to the frame), its mean absolute difference from the image is below that of the ring's
    per-channel median colour. Non-finite pixels are left out of both; a ring with no finite pixel
    (a mask covering the whole frame, an all-NaN render) gives False: the view keeps no observed part."""
    ker = np.ones((3, 3), np.uint8)
    ring = cv2.dilate(mask.astype(np.uint8), ker, iterations=int(ring_px)).astype(bool) & ~mask
    r, im = np.asarray(render, np.float64)[ring], np.asarray(image, np.float64)[ring]
    ok = np.isfinite(r).all(1) & np.isfinite(im).all(1)
    if not ok.any():
        return False
    r, im = r[ok], im[ok]
    return float(np.abs(r - im).mean()) < float(np.abs(im - np.median(im, 0)).mean())


def fit_trusted(scene: Scene, renders: Renders, i: int, mask: np.ndarray, cfg: RefineConfig) -> bool:
    """Whether view i's observed part may come from the fit: always without `cfg.fit_check` or
    with an empty `mask` (H, W) bool, else `fit_reproduces` of its render around the mask."""
    if not cfg.fit_check or not mask.any():
        return True
    return fit_reproduces(renders[i][0], scene.images[i], mask, cfg.fit_ring_px)


def split_view(
    scene: Scene,
    masks: list[np.ndarray],
    renders: Renders,
    i: int,
    train: list[int],
    cfg: RefineConfig,
    trusted: bool | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Step 3 for view i: its input mask split by the rules of `cfg` against the training views
    `train`, from `fit_renders`' `renders`. trusted: `fit_trusted`'s answer for the view when the
    caller has it (None: asked here). Returns (M^rmv_n (H, W) bool, the unseen core; the
    observed part's colours from the captures (H, W, 3), None without `cfg.warp_tol`; the pixels
    those colours cover (H, W) bool)."""
    mask = np.asarray(masks[i], bool)
    alpha, d = renders[i][1], renders[i][2]
    if not (fit_trusted(scene, renders, i, mask, cfg) if trusted is None else trusted):
        # a fit that cannot reproduce this view around the mask is not trusted inside it
        return mask.copy(), None, np.zeros_like(mask)
    cams = {j: scene.cameras[j] for j in train}
    covered = mask & (alpha >= cfg.alpha_thresh)
    if cfg.view_check > 0:
        # Covered is not enough: through the hole the object leaves, G^rmv may show a surface
        # that lies behind one nobody saw (the floor under the table under the object). A
        # covered pixel counts as observed only where its rendered surface point is seen by
        # another view, outside that view's mask, at the depth that view renders.
        srcs = {**cams, i: scene.cameras[i]}  # a test view is judged by the training views
        covered &= seen_elsewhere(srcs, masks, renders, i, covered, cfg.view_check, cfg.alpha_thresh,
                                  cfg.ray_samples, cfg.min_fraction)  # fmt: skip
    refined = fill_islands(mask & ~covered, mask, cfg.island_px)
    if cfg.warp_tol > 0 and mask.any():
        # The observed part's colours from the captures (observed_warp's doc).
        srcs = {j: scene.cameras[j] for j in train if j != i}
        warped, found, _ = warp_observed(
            srcs, {j: scene.images[j] for j in srcs}, {j: masks[j] for j in srcs}, d,
            {j: renders[j][3] for j in srcs}, scene.cameras[i], mask, cfg.warp_tol,
        )  # fmt: skip
    else:
        warped, found = None, np.zeros_like(mask)
    if mask.any() and not mask.all() and cfg.see_through > 0:
        # The older rule: deeper than the surroundings' depth carried inward (misfires where
        # the mask spans a depth edge, e.g. a wall behind a table; measured in the module doc).
        from coin_cl.gs.depth_prior import inpaint_depth

        refined |= mask & (d > (1 + cfg.see_through) * inpaint_depth(d, mask))
    if cfg.grow_px > 0 and refined.any():
        ker = np.ones((2 * cfg.grow_px + 1,) * 2, np.uint8)
        refined = cv2.dilate(refined.astype(np.uint8), ker).astype(bool) & mask
    if cfg.enclosed:
        refined |= enclosed_parts(mask & ~refined, mask)
    # A pixel whose surface another view captured, unoccluded and outside its mask, is
    # observed: the see-through rule, the growth and the enclosure (guesses from the render) yield to it.
    refined &= ~found
    return refined, warped, found


def fit_renders(
    scene: Scene,
    masks: list[np.ndarray],
    train: list[int],
    gs_dir: Path,
    cfg: RefineConfig,
    iters: int,
    seed: int = 0,
    device: DeviceLike = None,
    also: list[int] | tuple[int, ...] = (),
    vote_masks: list[np.ndarray] | None = None,
) -> tuple[Renders, int, int]:
    """Steps 1-3 of the module doc up to the renders: the object-present fit (`iters` steps,
    resumable in `gs_dir`), G^rmv (the vote against `vote_masks`, default `masks`), and per view
    of `train` + `also` the tuple of `Renders` (G^rmv's depth in float64). Returns (renders,
    Gaussians fitted, Gaussians removed)."""
    from coin_cl.gs.base import splat
    from coin_cl.gs.prune import in_masks
    from coin_cl.pipeline.refgs import fit_captured

    tr = fit_captured(scene, train, cfg.model, iters, seed, "opencl", device, Path(gs_dir))
    model, views = tr.model, tr.train_views
    centre = torch.stack([v.camera.center_t for v in views]).mean(0)
    with torch.no_grad():
        g = model.export_gaussians(centre)
    means = g.means.float()
    voters = [(vote_masks or masks)[i] for i in train]
    keep = torch.from_numpy(~in_masks(means.numpy(), [v.camera for v in views], voters, cfg.min_fraction))
    n_removed = int((~keep).sum())
    log.info("refine masks: %d of %d Gaussians removed (inside the masks in >= %.0f%% of the views "
             "seeing them)", n_removed, len(means), 100 * cfg.min_fraction)  # fmt: skip
    if not bool(keep.any()):
        raise ValueError(
            "refine masks: every Gaussian lies inside the masks; the masks cover the whole scene?"
        )
    kept = g.subset(keep).gaussians()  # the renderer's view: activated scales, opacities, colours
    m, q, s_own, op, rgb = kept.means, kept.quats, kept.scales, kept.opacities, kept.colors.clamp(0, 1)
    from coin_cl.gs.data import Camera as ViewCamera

    # the fit with the object: the depth of the captured surface, in front of which a view sees through
    every = g.gaussians()
    full = (every.means, every.quats, every.scales, every.opacities, every.colors.clamp(0, 1))
    extra = [ViewCamera.from_any(scene.cameras[i], name=str(i)) for i in also]
    renders = {}
    for cam_v, i in zip([v.camera for v in views] + extra, list(train) + list(also), strict=True):
        V, K = cam_v.viewmat_t, cam_v.K_t
        z = (m @ V[:3, :3].T + V[:3, 3])[:, 2].clamp_min(1e-6)
        fixed = (cfg.splat_px * z / K[0, 0])[:, None].expand(-1, 3).contiguous()
        with torch.no_grad():
            img, _, depth, _ = splat(cam_v, m, q, s_own, op, rgb, backend="opencl", background=None,
                                     return_depth=True, training=False, device=device)  # fmt: skip
            _, alpha, _, _ = splat(cam_v, m, q, fixed, op, rgb, backend="opencl", background=None,
                                   return_depth=False, training=False, device=device)  # fmt: skip
            _, a_full, d_full, _ = splat(cam_v, *full, backend="opencl", background=None, return_depth=True,
                                         training=False, device=device)  # fmt: skip
        d_cap = np.where(a_full.numpy() > 0.5, d_full.numpy(), 0.0)  # the captured surface (object included)
        renders[i] = (img.clamp(0, 1).numpy(), alpha.numpy(), depth.numpy().astype(np.float64), d_cap)
    return renders, int(len(means)), n_removed


def seen_elsewhere(
    cams: dict[int, Camera],
    masks: list[np.ndarray],
    renders: Renders,
    n: int,
    pixels: np.ndarray,
    tol: float,
    alpha_min: float,
    ray_samples: int = 24,
    hull_fraction: float = 0.5,
) -> np.ndarray:
    """Which of view n's `pixels` ((H, W) bool) another view observes, with nothing unknown in
    between. Observed: the pixel's rendered surface point X (the expected depth of `renders[n]`)
    projects into some other view m of `cams` in frame, outside `masks[m]`, where m's render is
    opaque (alpha >= `alpha_min`) and its depth agrees with X's camera z within `tol` (relative);
    and every one of `ray_samples` points on n's ray in front of X is known to be empty: in front
    of the surface n captured there, inside the object's volume (in the masks of at least
    `hull_fraction` of the views that see it: the object is removed), or in front of the surface
    another view renders, outside its mask (that view sees through it). A ray that crosses
    unknown space (the table under the object) may show a surface behind one nobody saw.
    `renders`: `fit_renders`' (`Renders`; the fixed-scale alpha, the expected depth of the
    object-free model and the captured surface's depth are read). Returns (H, W) bool, a subset
    of `pixels`."""
    ys, xs = np.nonzero(pixels)
    out = np.zeros(np.shape(pixels), bool)
    if not len(ys):
        return out
    d = renders[n][2][ys, xs]
    ok = np.isfinite(d) & (d > 0)
    ys, xs, d = ys[ok], xs[ok], d[ok]
    pts = cams[n].unproject(np.stack([xs + 0.5, ys + 0.5], 1), d)
    seen = np.zeros(len(pts), bool)
    for m, cam in cams.items():
        if m == n:
            continue
        px, inside = cam.pixels(pts)
        _, z = cam.project(pts)
        a, dm = renders[m][1][px[:, 1], px[:, 0]], renders[m][2][px[:, 1], px[:, 0]]
        free = ~np.asarray(masks[m], bool)[px[:, 1], px[:, 0]]
        with np.errstate(invalid="ignore"):
            seen |= inside & free & (a >= alpha_min) & (np.abs(z - dm) <= tol * dm)
    if ray_samples > 0 and seen.any():
        ys, xs, d = ys[seen], xs[seen], d[seen]
        t = d[:, None] * np.linspace(0.0, 1.0 - tol, ray_samples + 2)[1:-1]  # (P, S) camera z
        ok = t <= renders[n][3][ys, xs][:, None] * (1 - tol)  # n itself sees through
        uv = np.repeat(np.stack([xs + 0.5, ys + 0.5], 1), t.shape[1], axis=0)
        ys_ = cams[n].unproject(uv, t.reshape(-1))
        ok = ok.reshape(-1)
        from coin_cl.gs.prune import in_masks

        others = [m for m in cams if m != n]
        ok |= in_masks(ys_, [cams[m] for m in others], [masks[m] for m in others], hull_fraction)
        for m in others:
            px, inside = cams[m].pixels(ys_)
            _, z = cams[m].project(ys_)
            a, dm = renders[m][1][px[:, 1], px[:, 0]], renders[m][2][px[:, 1], px[:, 0]]
            free = ~np.asarray(masks[m], bool)[px[:, 1], px[:, 0]]
            with np.errstate(invalid="ignore"):
                ok |= inside & free & (a >= alpha_min) & (z < (1 - tol) * dm)
        clear = ok.reshape(-1, t.shape[1]).all(1)
        ys, xs = ys[clear], xs[clear]
        out[ys, xs] = True
        return out
    out[ys[seen], xs[seen]] = True
    return out


def vote_ring(width: int, height: int, dilate: int) -> int:
    """Extra 5x5 dilation iterations (2 px each) of the training masks for step 2's vote: up to the
    default ring (`scene.masks.auto_dilation`) when the training masks are dilated less (`dilate`
    iterations; `--mask-dilate 0` keeps exact masks), 0 otherwise. The unanimous vote removes a
    Gaussian only if it lies inside every mask that has it in frame; a tight mask leaves Gaussians
    of the object's silhouette outside it in some view, they survive and cover the footprint, and
    the split takes it for observed (measured on the demo room with exact masks: the unseen core's
    recall 0.94 dilated, 0.83 not)."""
    from coin_cl.scene.masks import auto_dilation

    return max(0, auto_dilation(width, height) - int(dilate))


def read_refined(scene: Scene, folder: Path, train: list[int], masks: list[np.ndarray]):
    """(images, masks) per scene view after `refine_masks`: the stage's base images and refined
    masks for `train`, the scene's and `masks` elsewhere."""
    from coin_cl.scene.io import read_image
    from coin_cl.scene.masks import read_mask

    images, out = list(scene.images), list(masks)
    for i in train:
        stem = Path(scene.cameras[i].name).stem
        images[i] = read_image(Path(folder) / "images" / f"{stem}.png")
        out[i] = read_mask(Path(folder) / "masks" / f"{stem}.png", masks[i].shape)
    return images, out
