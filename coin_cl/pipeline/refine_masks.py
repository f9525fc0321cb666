"""3D-first refined masks (paper supplement C.2) for 360-degree and other wide captures: stage
`0_refine`, run before stage 1 when `CoInConfig.inpaint_region == "refined"`
(`coin-cl run --inpaint-region refined`).

A 2D-first pipeline inpaints the whole object mask in every view, although a wide capture sees most
of what the object hides from some other view. Here:

1. a GS (`RefineConfig.model`, `iters` steps) is fitted to the captured training views, object and all;
2. its Gaussians are exported (`export_gaussians`; a Scaffold model is decoded at the mean camera
   centre) and those whose centre projects inside the mask in at least `min_fraction` of the
   training views that see it are removed (`prune_points_in_masks`' vote: the object is inside the
   mask from every view, background behind it only from some), leaving G^rmv;
3. G^rmv is rendered with fixed scales: every Gaussian an isotropic disk of `splat_px` pixels
   (its world radius set from its camera z in that view, so near and far surfaces are judged
   alike), so that coverage means a surface point nearby, not one large Gaussian smeared over the
   hole; the refined mask M^rmv_n is the input mask where that alpha is
   below `alpha_thresh` (nothing of the remaining scene lands there: truly unseen), plus the
   covered pixels whose rendered depth lies more than `see_through` beyond the surroundings' depth
   carried inward (the removal exposed what is behind a surface nobody saw, e.g. the floor under
   the table under the object), grown by `grow_px` pixels inside the input mask;
4. R^rmv_n, the render of G^rmv with its own scales, stands in for the captured pixels in the input
   mask outside M^rmv_n.

The later stages then inpaint M^rmv_n only, with R^rmv_n outside it in the mask. Files (stage folder):
masks/<stem>.png (M^rmv_n), images/<stem>.png (the capture, R^rmv_n in the input mask),
renders/<stem>.png (R^rmv_n), areas.json (per view: input and refined mask pixels), gs/ (the fit).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from coin_cl.scene.io import to_uint8, write_png

log = logging.getLogger(__name__)


@dataclass
class RefineConfig:
    """iters: steps of the object-present fit (None: the pipeline's Ref-GS step count). model:
    "3dgs" or "scaffold". min_fraction: removal vote (step 2). splat_px: the fixed render scale in
    pixels (step 3; about the spacing of a fitted GS's Gaussians on a surface). alpha_thresh:
    coverage below which a mask pixel is unseen. grow_px: dilation of M^rmv_n inside the input
    mask. see_through: a covered mask pixel whose rendered depth exceeds the surroundings'
    (inpainted inward) by more than this fraction is unseen too (0: off)."""

    iters: int | None = None
    model: str = "3dgs"
    min_fraction: float = 0.5
    splat_px: float = 1.5
    alpha_thresh: float = 0.5
    grow_px: int = 1
    see_through: float = 0.15


def refine_masks(
    scene: Any,
    masks: list[np.ndarray],
    train: list[int],
    out_dir: Path,
    cfg: RefineConfig,
    iters: int,
    seed: int = 0,
    device: Any = None,
) -> dict[str, Any]:
    """Steps 1-4 of the module doc for the training views `train` of `scene` with input `masks`
    (per view (H, W) bool); writes the stage files into `out_dir`. `iters` is used when
    `cfg.iters` is None. Returns JSON-able figures: per-view areas and the refined / input ratio.
    A view with an empty input mask keeps an empty refined mask."""
    from coin_cl.gs.base import splat
    from coin_cl.gs.prune import in_masks
    from coin_cl.scene.masks import write_mask

    out_dir = Path(out_dir)
    n_iters = int(cfg.iters if cfg.iters is not None else iters)
    from coin_cl.pipeline.refgs import fit_captured

    tr = fit_captured(scene, train, cfg.model, n_iters, seed, "opencl", device, out_dir / "gs")
    model, views = tr.model, tr.train_views
    centre = torch.stack([v.camera.center_t for v in views]).mean(0)
    with torch.no_grad():
        g = model.export_gaussians(centre)
    means = g.means.float()
    keep = torch.from_numpy(
        ~in_masks(means.numpy(), [v.camera for v in views], [masks[i] for i in train], cfg.min_fraction)
    )
    n_removed = int((~keep).sum())
    log.info("refine masks: %d of %d Gaussians removed (inside the masks in >= %.0f%% of the views "
             "seeing them)", n_removed, len(means), 100 * cfg.min_fraction)  # fmt: skip
    if not bool(keep.any()):
        raise ValueError(
            "refine masks: every Gaussian lies inside the masks; the masks cover the whole scene?"
        )
    kept = g.subset(keep).gaussians()  # the renderer's view: activated scales, opacities, colours
    m, q, s_own, op, rgb = kept.means, kept.quats, kept.scales, kept.opacities, kept.colors.clamp(0, 1)
    areas = {}
    for v, i in zip(views, train, strict=True):
        stem = Path(scene.cameras[i].name).stem
        mask = np.asarray(masks[i], bool)
        V, K = v.camera.viewmat_t, v.camera.K_t
        z = (m @ V[:3, :3].T + V[:3, 3])[:, 2].clamp_min(1e-6)
        fixed = (cfg.splat_px * z / K[0, 0])[:, None].expand(-1, 3).contiguous()
        with torch.no_grad():
            img, _, depth, _ = splat(v.camera, m, q, s_own, op, rgb, backend="opencl", background=None,
                                     return_depth=True, training=False, device=device)  # fmt: skip
            _, alpha, _, _ = splat(v.camera, m, q, fixed, op, rgb, backend="opencl", background=None,
                                   return_depth=False, training=False, device=device)  # fmt: skip
        render = img.clamp(0, 1).numpy()
        refined = mask & (alpha.numpy() < cfg.alpha_thresh)
        if mask.any() and not mask.all() and cfg.see_through > 0:
            # Removing the object can expose what lies *behind* a surface nobody saw (the floor
            # under a table): covered, but deeper than the surroundings' depth carried inward.
            from coin_cl.gs.depth_prior import inpaint_depth

            d = depth.numpy().astype(np.float64)
            around = inpaint_depth(d, mask)
            refined |= mask & (d > (1 + cfg.see_through) * around)
        if cfg.grow_px > 0 and refined.any():
            ker = np.ones((2 * cfg.grow_px + 1,) * 2, np.uint8)
            refined = cv2.dilate(refined.astype(np.uint8), ker).astype(bool) & mask
        base = np.where((mask & ~refined)[..., None], render, scene.images[i]).astype(np.float32)
        write_png(out_dir / "renders" / f"{stem}.png", to_uint8(render))
        write_png(out_dir / "images" / f"{stem}.png", to_uint8(base))
        write_mask(out_dir / "masks" / f"{stem}.png", refined)
        areas[stem] = {"input_px": int(mask.sum()), "refined_px": int(refined.sum())}
        log.info("refine masks: view %s: %d -> %d px (%.0f%%)", stem, mask.sum(), refined.sum(),
                 100 * refined.sum() / max(1, mask.sum()))  # fmt: skip
    (out_dir / "areas.json").write_text(json.dumps(areas, indent=1, sort_keys=True))
    tot_in = sum(a["input_px"] for a in areas.values())
    tot_ref = sum(a["refined_px"] for a in areas.values())
    return {
        "iters": n_iters,
        "model": cfg.model,
        "n_gaussians": int(len(means)),
        "n_removed": n_removed,
        "splat_px": cfg.splat_px,
        "input_px": tot_in,
        "refined_px": tot_ref,
        # refined over input mask area over all training views (1 = nothing gained; 0 with empty masks)
        "refined_ratio": tot_ref / tot_in if tot_in else 0.0,
        "areas": areas,
    }


def read_refined(scene: Any, folder: Path, train: list[int], masks: list[np.ndarray]):
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
