"""Stage 3, Consistency Loss Guidance (CLG, paper 4.3): re-inpaint every non-reference view with the
diffusion sampler steered toward 3D consistency with the reference view k.

For each view n (not k, non-empty mask; other views are skipped and logged) the sampler of
`coin_cl.diffusion` runs on a square crop around the mask (the same crop rule as stage 1,
`diffusion.inpaint2d.crop_box`), resized to the model's working size (64 for the scene prior, 512
for Stable Diffusion 2), with FreeDoM energy guidance on the decoded x0 prediction X. The energy
and its geometry (crop cameras, the intermediate camera phi, the support S) are in
`coin_cl.pipeline.clg_energy`; the reprojection tools (the reference warped into a view, the
consistency residual, the sampler-free `warp_fill`) in `coin_cl.pipeline.reprojection`.

Output: the last step's decoded x0 prediction, clamped, brought back to the crop with its band
above half the working size replaced by the reference's detail warped through P_k (where P_k
reaches) or I^_n's (`coin_cl.pipeline.clg_detail`: the 64 px sample alone is blurrier than I^_n),
the low band's colours matched to the reference warped into the view, its chroma taken from there
pixel by pixel (`clg_detail.match_colour`; the unmatched composite is a second candidate), and
pasted into I^_n inside the mask only (`diffusion.inpaint2d.paste`, feathered inward), so every
pixel outside the mask is bit-identical to I^_n; the sampler starts from I^_n's crop noised half
way (`CLGConfig.strength`). The no-worse guard (`coin_cl.pipeline.clg_guard`) writes the candidate
that is not worse than I^_n with the lowest residual to the reference, or I^_n, as
`images/<stem>.png` with `views/<stem>.json` (figures). A view whose PNG exists is not redone
(resume). Randomness: view n samples with seed + n.

Before Ref-GS exists, `coin_cl.pipeline.reference.reference_points` builds P_k from any depth map
of the reference view (GS render, ground truth, ...) with the same margin rule as the Ref-GS stage.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from coin_cl.diffusion.sampling import Denoiser
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.clg_detail import ReferenceView
from coin_cl.pipeline.clg_guard import pick
from coin_cl.pipeline.clg_view import sample_view, warp_view
from coin_cl.scene.io import atomic_write, view_stem, write_png
from coin_cl.schema import CLG_VIEW, SD2_PLAN, parse_optional, run_folder_fix

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.pipeline.run_inputs import RunInputs
    from coin_cl.pipeline.runner import StageContext
    from coin_cl.scene import Camera, Scene

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------------------------
# run_clg and its pieces


def _check_image(a: Any, H: int, W: int, what: str, ch: int | None = 3) -> np.ndarray:
    a = np.asarray(a)
    want = (H, W) if ch is None else (H, W, ch)
    if a.shape != want:
        raise ValueError(f"{what} has shape {a.shape}, expected {want}")
    if ch is not None and not np.isfinite(a).all():
        raise ValueError(f"{what} contains NaN/Inf")
    return a.astype(np.float32, copy=False) if ch is not None else a


def _depth_of(
    depths: Sequence[np.ndarray | None] | None, n: int, H: int, W: int, what: str
) -> np.ndarray | None:
    if depths is None or depths[n] is None:
        return None
    return _check_image(depths[n], H, W, what, None)


def _usable_points(points: np.ndarray, max_points: int) -> np.ndarray:
    """P_k [M, 3] float32 with non-finite rows dropped (logged), thinned evenly to max_points."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [M, 3], got {points.shape}")
    finite = np.isfinite(points).all(1)
    if not finite.all():
        log.warning("CLG: %d of %d points of P_k are not finite; dropped", int((~finite).sum()), len(points))
        points = points[finite]
    if len(points) > max_points:
        points = points[np.linspace(0, len(points) - 1, max_points).round().astype(np.int64)]
    return points


def _check_sequences(reference: int, views: Sequence[int], cameras: Sequence[Camera], inpaints: Sequence[Any],
                     renders: Sequence[Any], depths: Sequence[Any] | None,
                     masks: Sequence[Any]) -> None:  # fmt: skip
    n_views = len(cameras)
    for name, seq in (("inpaints", inpaints), ("renders", renders), ("masks", masks)):
        if len(seq) != n_views:
            raise ValueError(f"{name} has {len(seq)} entries for {n_views} cameras")
    if depths is not None and len(depths) != n_views:
        raise ValueError(f"depths has {len(depths)} entries for {n_views} cameras")
    if not 0 <= int(reference) < n_views:
        raise ValueError(f"reference view {reference} is not one of the {n_views} views")
    bad = [v for v in views if not 0 <= int(v) < n_views]
    if bad:
        raise ValueError(f"unknown views {bad} (the scene has {n_views})")


def _write_view(js: Path, png: Path, rec: dict[str, Any], out: np.ndarray) -> None:
    # the JSON first: a PNG present means the view is complete (resume checks the PNG)
    atomic_write(js, lambda p, r=rec: p.write_text(json.dumps(r, indent=1)))
    write_png(png, out)


def run_clg(
    reference: int,
    views: Sequence[int],
    cameras: Sequence[Camera],
    inpaints: Sequence[np.ndarray | None],
    renders: Sequence[np.ndarray | None],
    depths: Sequence[np.ndarray | None] | None,
    masks: Sequence[np.ndarray],
    points: np.ndarray,
    denoiser: Denoiser | None,
    features: Callable | None,
    out_dir: str | Path,
    cfg: CLGConfig | None = None,
    device: DeviceLike = None,
) -> dict[str, Any]:
    """Consistency Loss Guidance for `views` against the reference view (see the module docstring).

    Args:
        reference: index k of the reference view (into the per-view sequences).
        views: view indices to process; the reference and views with an empty mask are skipped
            (logged and recorded).
        cameras: per view, a `Camera` (K [3, 3], viewmat [4, 4] world-to-camera, width, height, name).
        inpaints: per view, I^_n [H, W, 3] float in [0, 1] (already composited with the captured
            image outside the mask: it is also the output outside the mask); needed for k and `views`.
        renders: per view, the GS render R_n [H, W, 3] float (the (1 - m) term).
        depths: per view, rendered camera z [H, W] (occlusion tests; non-finite = empty) or None.
        masks: per view, [H, W] bool (True = inpaint).
        points: P_k [M, 3] world points (see `reference.reference_points`); NaN rows are dropped by the warp.
        denoiser: a `coin_cl.diffusion` Denoiser with make_condition (scene prior or SD2); None with
            `cfg.sample` False (as `features`).
        features: f_hr, a differentiable (1, 3, h, w) [0, 1] -> (1, C, h, w) extractor.
        out_dir: writes images/<stem>.png and views/<stem>.json; existing PNGs are kept (resume).
        cfg: `CLGConfig`. device: OpenCL device for the warp (Runtime, name, or None).
    Returns:
        {"views": {stem: record}, "n_guided", "n_skipped", "n_resumed", "steps", "model", ...};
        a record has status 'guided' | 'propagated' | 'kept input' | 'resumed' | 'skipped' (+ reason)
        and, when run, the energy
        of I^_n and of the output, the guided steps' energies, the consistency residuals before and
        after, support sizes and seconds.
    """
    from tqdm import tqdm

    cfg = cfg or CLGConfig()
    _check_sequences(reference, views, cameras, inpaints, renders, depths, masks)
    points = _usable_points(points, cfg.max_points)
    k = int(reference)
    cam_k = cameras[k]
    Hk, Wk = cam_k.height, cam_k.width
    ref = ReferenceView(k, cam_k, _check_image(inpaints[k], Hk, Wk, f"inpaint of the reference view {k}"),
                     _depth_of(depths, k, Hk, Wk, "depth k"), points, np.asarray(masks[k], bool))  # fmt: skip
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "views").mkdir(parents=True, exist_ok=True)
    if cfg.sample and (denoiser is None or features is None):
        raise ValueError(
            "CLG with the sampler needs a denoiser and a feature extractor (or CLGConfig.sample=False)"
        )
    records: dict[str, dict[str, Any]] = {}
    bar = tqdm(list(views), desc="CLG views", unit="view", disable=not cfg.progress)
    for n in bar:
        n = int(n)
        cam = cameras[n]
        stem = view_stem(getattr(cam, "name", ""), n)
        bar.set_postfix_str(stem)
        mask = np.asarray(masks[n], bool)
        if n == k:
            records[stem] = {"view": n, "status": "skipped", "reason": "reference view"}
            log.info("CLG: view %d (%s) skipped: the reference view", n, stem)
            continue
        if mask.shape != (cam.height, cam.width):
            raise ValueError(f"mask of view {n} has shape {mask.shape}, expected {(cam.height, cam.width)}")
        if not mask.any():
            records[stem] = {"view": n, "status": "skipped", "reason": "empty mask"}
            log.info("CLG: view %d (%s) skipped: empty mask", n, stem)
            continue
        png, js = out_dir / "images" / f"{stem}.png", out_dir / "views" / f"{stem}.json"
        if png.is_file():
            rec = parse_optional(js, CLG_VIEW, run_folder_fix(js, "its view is recorded again")) or {
                "view": n
            }
            records[stem] = rec | {"status": "resumed"}
            log.info("CLG: view %d (%s) already written: kept", n, stem)
            continue
        t0 = time.perf_counter()
        try:
            inp_n = _check_image(inpaints[n], cam.height, cam.width, f"inpaint of view {n}")
            if renders[n] is None:
                raise ValueError(f"view {n} has no render R_n")
            ren_n = _check_image(renders[n], cam.height, cam.width, f"render of view {n}")
            depth_n = _depth_of(depths, n, cam.height, cam.width, f"depth of view {n}")
            if not cfg.sample:
                out, rec = warp_view(n, cam, inp_n, ren_n, depth_n, mask, ref, device, cfg.propagate,
                                     cfg.detail_gain_max)  # fmt: skip
                log.info("CLG (warp, no sampler%s): view %d (%s): %d of %d hole px supported, "
                         "residual %.4f -> %.4f", ", harmonised" if cfg.propagate else "", n, stem,
                         rec["support_px"], rec["hole_px"],
                         rec["residual_before"], rec["residual_after"])  # fmt: skip
                candidates = [(out, rec)]
            else:
                assert denoiser is not None and features is not None
                candidates = sample_view(n, stem, cam, inp_n, ren_n, depth_n, mask, ref, denoiser, features,
                                         cfg, device)  # fmt: skip
                out, rec = candidates[0]
        except (ValueError, RuntimeError) as exc:  # say which view, whatever failed inside
            raise type(exc)(f"CLG, view {n} ({stem}): {exc}") from exc
        if cfg.keep_if_worse and (cfg.sample or cfg.warp_guard):
            out, rec = pick(inp_n, candidates, mask, cfg)
            if rec["status"] == "kept input":
                log.info("CLG: view %d (%s) keeps its input I^_n: the %s image is worse (%s)", n, stem,
                         "guided" if cfg.sample else "warped", "; ".join(rec["kept_because"]))  # fmt: skip
        rec["seconds"] = time.perf_counter() - t0
        _write_view(js, png, rec, out)
        records[stem] = rec
        if cfg.sample:
            log.info("CLG: view %d (%s): energy %.4f -> %.4f, residual %.4f -> %.4f, %.1f s", n, stem,
                     rec["energy_input"], rec["energy_output"], rec["residual_before"], rec["residual_after"],
                     rec["seconds"])  # fmt: skip
    bar.close()
    status = [r["status"] for r in records.values()]
    return {
        "views": records,
        "n_guided": sum(s in ("guided", "unguided", "warped", "propagated") for s in status),
        "n_propagated": status.count("propagated"),
        "n_kept_input": status.count("kept input"),
        "n_skipped": status.count("skipped"),
        "n_resumed": status.count("resumed"),
        "steps": cfg.num_steps(denoiser) if cfg.sample else 0,
        "model": getattr(denoiser, "name", type(denoiser).__name__) if cfg.sample else "none (warp only)",
        "features": getattr(features, "name", type(features).__name__) if cfg.sample else None,
        "n_points": int(len(points)),
        "reference": k,
    }


# ----------------------------------------------------------------------------------------------------
# the pipeline stage


def _stage_inputs(
    ctx: StageContext[RunInputs], scene: Scene, masks: list[np.ndarray], train: list[int]
) -> tuple[list, list, list]:
    """(inpaints I^_n composited, renders R_n, depths masked to alpha > 0.5) per scene view, None
    outside the training views, from the stage folders 1_inpaint and 2_refgs."""
    from coin_cl.gs.targets import composite_targets
    from coin_cl.pipeline.inpaint2d import read_inpaints
    from coin_cl.scene.io import read_image

    inp = read_inpaints(scene, ctx.inputs["1_inpaint"], train)
    inpaints: list[np.ndarray | None] = [None] * len(scene)
    for i in train:
        inpaints[i] = composite_targets(inp[i], scene.images[i], masks[i])
    gs = ctx.inputs["2_refgs"]
    renders: list[np.ndarray | None] = [None] * len(scene)
    depths: list[np.ndarray | None] = [None] * len(scene)
    for i in train:
        stem = view_stem(scene.cameras[i].name, i)
        renders[i] = read_image(gs / "renders" / f"{stem}.png")
        d = np.load(gs / "depths" / f"{stem}.npy")
        a = gs / "alphas" / f"{stem}.npy"
        if a.is_file():
            d = np.where(np.load(a) > 0.5, d, np.nan)  # depth means a surface only where alpha > 0.5
        depths[i] = d
    return inpaints, renders, depths


def _stage_denoiser(
    ctx: StageContext[RunInputs], scene: Scene, masks: list[np.ndarray], train: list[int]
) -> Denoiser:
    """Stable Diffusion 2 when configured, else the scene prior of stage 1 (trained here when its
    cache is not in 1_inpaint: never written into an earlier stage's folder)."""
    from coin_cl.diffusion.scene_prior import cache_key
    from coin_cl.pipeline.inpaint2d import planned_config, stage_prior
    from coin_cl.pipeline.models import sd2_denoiser

    ccfg = ctx.run.cfg
    sd2 = sd2_denoiser(ccfg.sd_path)
    if sd2 is not None:
        return sd2
    cam = scene.cameras[train[0]]
    icfg = planned_config(ccfg.inpaint2d, ctx.run.plan, ccfg.seed, cam.width, cam.height)
    folder = ctx.inputs["1_inpaint"]
    key = cache_key([scene.images[i] for i in train], [masks[i] for i in train], icfg.prior)
    if not (folder / f"scene_prior_{key}.pt").is_file():
        folder = ctx.out  # never write into an earlier stage's folder (its manifest hashes it)
    return stage_prior(scene, masks, train, icfg, folder)


def stage_clg(
    ctx: StageContext[RunInputs], scene: Scene | None = None, masks: list[np.ndarray] | None = None
) -> dict[str, Any]:
    """Stage 3_clg of `coin_cl.pipeline.coin`: reads 1_inpaint (I^_n, the scene prior's cache) and
    2_refgs (renders/, depths/, alphas/, reference_points.ply); writes images/<stem>.png per guided view.
    scene, masks: the views as the pipeline's stages see them (default: the run's, `ctx.run`)."""
    from dataclasses import replace

    from coin_cl.pipeline.reference import reference_points

    scene = ctx.run.scene if scene is None else scene
    masks = ctx.run.masks if masks is None else masks
    train = list(scene.train_idx)
    k = int(ctx.run.ref)
    ccfg = ctx.run.cfg
    cfg: CLGConfig = ccfg.clg_settings()  # the run's seed and prompt where CLGConfig leaves them None
    inpaints, renders, depths = _stage_inputs(ctx, scene, masks, train)
    ply = ctx.inputs["2_refgs"] / "reference_points.ply"
    if ply.is_file():
        from coin_cl.scene.ply import read_points_ply

        points, _ = read_points_ply(ply)
        ctx.note(f"P_k: {len(points)} points from {ply.name}")
    else:
        points = reference_points(scene.cameras[k], depths[k], masks[k])
        ctx.note(f"P_k: {len(points)} points unprojected from the reference render's depth")
    sd2_plan = ctx.inputs["1_inpaint"] / "sd2.json"
    sd2 = parse_optional(sd2_plan, SD2_PLAN, run_folder_fix(sd2_plan, "stage 1 runs again"))
    if cfg.sample and sd2 is not None and sd2["mode"] == "reference_only":
        # SD2's CPU-practical mode: stage 1 ran SD2 on the reference only; no view here calls
        # it: each hole pixel takes the reference warped through P_k where it reaches, and the view's
        # initial (embedded) inpaint elsewhere, which stands in for R_n in `warp_fill`
        cfg = replace(cfg, sample=False, warp_guard=True)
        renders = inpaints
        ctx.note("SD2 reference_only: no sampler; each view takes the reference warped through P_k where "
                 "P_k reaches and its initial inpaint elsewhere, and keeps its input where that is "
                 "worse")  # fmt: skip
    if cfg.sample:
        from coin_cl.pipeline.coin_plan import clg_samples

        if not clg_samples(ccfg):
            cfg = replace(cfg, sample=False, warp_guard=True)
            ctx.note("no Stable Diffusion 2 and CLGConfig.prior_sampler off: CLG runs without a sampler "
                     "(CLGConfig.without_sampler): each view's hole takes the reference warped through P_k, "
                     "blended into the view's own surroundings, where that is no worse than its initial "
                     "inpaint")  # fmt: skip
    denoiser, extractor = None, None
    if cfg.sample:
        from coin_cl.diffusion.features import make_feature_extractor

        denoiser = _stage_denoiser(ctx, scene, masks, train)
        ctx.note(f"CLG model: {denoiser.name}")
        extractor, fname = make_feature_extractor(ccfg.dino_path)
        ctx.note(f"CLG features: {fname}")
    res = run_clg(k, train, scene.cameras, inpaints, renders, depths, masks, points, denoiser, extractor,
                  ctx.out, cfg, device=ccfg.device)  # fmt: skip
    for stem, r in res["views"].items():
        if r["status"] == "skipped":
            ctx.note(f"view {stem} skipped: {r['reason']}")
        elif r["status"] == "kept input":
            ctx.note(f"view {stem} keeps its initial inpaint: {'; '.join(r['kept_because'])}")
    done = [r for r in res["views"].values() if "texture_input" in r]
    if done:
        t_in = float(np.mean([r["texture_input"] for r in done]))
        t_out = float(np.mean([r["texture_input" if r["status"] == "kept input" else "texture_output"]
                               for r in done]))  # fmt: skip
        res["texture_input"], res["texture_written"] = t_in, t_out
        ctx.note(f"texture in the masks: initial inpaints {t_in:.4f}, CLG's images {t_out:.4f} "
                 f"({res['n_kept_input']} of {len(done)} views kept their input)")  # fmt: skip
    written_views = [r for r in res["views"].values() if r["status"] != "kept input"]
    gains = [r["detail_gain"] for r in written_views if "detail_gain" in r]
    if gains and max(gains) > 1.0:
        ctx.note(f"detail band topped up to the input's texture in {sum(g > 1.0 for g in gains)} of "
                 f"{len(gains)} written views (gain up to {max(gains):.3f})")  # fmt: skip
    return res
