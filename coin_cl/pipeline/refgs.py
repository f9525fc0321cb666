"""The Ref-GS stage (CoIn paper 4.2): the coarse Scaffold-GS scene trained on the
per-view inpaints I^_n, leaning toward one reference view k. CLG and TE-D stand on its outputs.

`run_refgs(scene, targets, out_dir, cfg, ...)` writes into `out_dir`:

    gs/ckpt.pt, gs/log.json, gs/cameras.json, gs/point_cloud.ply   the trainer's folder (resumable)
    renders/<stem>.png          R_n of every training view (uint8 RGB)
    depths/<stem>.npy           expected camera z of every training view [H, W] float32
    alphas/<stem>.npy           rendered alpha [H, W] float32 (depth is meaningful where > 0.5)
    reference_points.ply        P_k: the reference render's depth unprojected, with its colours
    depth_prior.npy / .json     the reference's depth prior D_k and its source (when depth loss is on)
    bg_depths/<stem>.npy        D_bg of every training view with a mask (when `cfg.bg_depth`)
    stage.json                  what `run_refgs` returns (paths and figures)

The JSON log (gs/log.json) carries under "refgs": the config, the reference, the prior's name,
the pruned point count; under "view_weights": the per-visit weight history and per-view summary.

P_k: `coin_cl.pipeline.reference.reference_points` on the reference's render depth, restricted to
rendered alpha > 0.5 (the margin rule `pk_margin_px` lives there too).

Budget: `iters` wins; else `budget_minutes` of Ref-GS become steps by the pipeline's rule
(`pipeline.budget.standalone_steps`: a timing probe on this machine and Ref-GS's measured step
cost) and the trainer also stops when the budget's training time is spent; neither: the published
30k steps. With `replan_seconds` (a CoIn run passes the stage's planned seconds), `iters` is planned
again from a few steps of Ref-GS's own model before it trains (`budget.refgs_steps_from_rate`).
Schedules (learning rates, densification, attention start and lr) are compressed to `iters` the
way `scaled_model_config` / `scaled_strategy` do. A rerun with the same `out_dir` continues from
the checkpoint with the first run's `iters` (a different request is logged and ignored).
"""

from __future__ import annotations

import gc
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from coin_cl.gs.background_depth import background_depths
from coin_cl.gs.data import Camera, View, init_points, scene_extent
from coin_cl.gs.depth_prior import DepthPrior, inpaint_depth, reference_depth_prior
from coin_cl.gs.model_kinds import build_model, scaled_model_config, scaled_strategy
from coin_cl.gs.prune import prune_points_in_masks
from coin_cl.gs.refgs import RefGSConfig, adaptive_weights_of, refgs_terms
from coin_cl.gs.targets import composite_targets
from coin_cl.gs.trainer import TrainConfig, Trainer
from coin_cl.pipeline.budget import (
    PROBE_STEPS,
    PROBE_WARMUP,
    probe_seconds_per_step,
    refgs_steps_from_rate,
    standalone_steps,
)
from coin_cl.pipeline.reference import choose_reference, pk_margin_px, reference_pixels, reference_points
from coin_cl.scene.io import view_stem, write_npy, write_png, write_text
from coin_cl.schema import DEPTH_PRIOR, REFGS_STAGE, parse, parse_optional, run_folder_fix
from coin_cl.timing import late_step_seconds, median_step_seconds

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Scene

log = logging.getLogger(__name__)

MIN_POINTS = 4  # sparse points the Gaussians need to start from

MONOCULAR_PRIOR = "monocular (Depth Anything V2 small, COIN_DEPTH_WEIGHTS)"
STAGE_JSON = "stage.json"


def fit_captured(scene: Scene, train_idx: Sequence[int], kind: str, iters: int, seed: int, backend: str,
                 device: DeviceLike, out: Path) -> Trainer:  # fmt: skip
    """A short GS (`kind` 'scaffold' or '3dgs', `iters` steps, default schedules compressed to
    them) fitted to the captured (unmasked) training images, resumable in `out`; the trained
    `Trainer` (its `model`, `train_views`)."""
    from coin_cl.gs.data import views_from_scene

    views = views_from_scene(scene, train_idx)
    pts, cols = init_points(scene, views)
    model = build_model(kind, pts, cols, scene_extent([v.camera for v in views]), seed,
                        scaled_model_config(kind, iters))  # fmt: skip
    model.device = device
    cfg = TrainConfig(model=kind, iters=iters, backend=backend, seed=seed, progress=True, ckpt_every=0,
                      export_ply=False)  # fmt: skip
    tr = Trainer(model, views, [], cfg, out, strategy=scaled_strategy(kind, iters))
    if tr.ckpt_path is not None and tr.ckpt_path.is_file():
        tr.load_checkpoint()
    tr.train()
    return tr


def _aux_gs_depth(scene: Scene, train_idx: Sequence[int], k: int, iters: int, seed: int, backend: str,
                  device: DeviceLike, out: Path) -> np.ndarray:  # fmt: skip
    """Depth of the reference view rendered by a short Scaffold-GS trained on the captured
    (unmasked) images: the last prior in `reference_depth_prior`'s order. [H, W] float32 camera z."""
    tr = fit_captured(scene, train_idx, "scaffold", iters, seed, backend, device, out)
    cam = scene.cameras[k]
    with torch.no_grad():
        r = tr.model.render(cam, tr.step, backend=backend, return_depth=True)
    d = r.depth.numpy().astype(np.float32)
    d[r.alpha.numpy() <= 0.5] = np.nan  # inpaint_depth fills non-finite pixels too
    return d


def _depth_prior(scene: Scene, train_idx: Sequence[int], k: int, iters: int, seed: int, backend: str,
                 device: DeviceLike, gs_depth: np.ndarray | None, out: Path,
                 aux_iters: int | None = None,
                 known_depth: np.ndarray | None = None) -> DepthPrior:  # fmt: skip
    """D_k in `reference_depth_prior`'s order, cached in out/depth_prior.npy (+ .json) so a rerun reuses it.
    known_depth: see `run_refgs`; its finite pixels replace the prior's."""
    npy, meta = out / "depth_prior.npy", out / "depth_prior.json"
    if npy.is_file() and meta.is_file():
        doc = parse(meta, DEPTH_PRIOR, run_folder_fix(meta, "the prior is made again"))
        return DepthPrior(np.load(npy, allow_pickle=False), doc["name"])
    if known_depth is not None and (getattr(scene, "priors", None) or {}).get("depth"):
        # The dataset's inpainted disparity shows the scene without the object: wrong on an insertion.
        log.info("known depth given: the dataset's (removal) depth prior is not used")
        scene = replace(scene, priors={n: v for n, v in scene.priors.items() if n != "depth"})
    if os.environ.get("COIN_DEPTH_WEIGHTS"):
        # No Depth Anything port exists in this package yet; say so rather than silently skip.
        log.warning("COIN_DEPTH_WEIGHTS is set but no monocular estimator is implemented; next prior")
    if gs_depth is None and not (getattr(scene, "priors", None) or {}).get("depth", {}).get(k) is not None:
        t = time.perf_counter()
        aux_iters = max(min(100, iters), iters // 5) if aux_iters is None else aux_iters
        log.info(
            "no dataset depth prior for view %d: training a %d-step GS on the captured images", k, aux_iters
        )
        gs_depth = _aux_gs_depth(scene, train_idx, k, aux_iters, seed, backend, device, out / "aux_gs")
        log.info("auxiliary GS for the depth prior: %.1f s", time.perf_counter() - t)
    prior = reference_depth_prior(scene, k, gs_depth=gs_depth, mask=np.asarray(scene.masks[k], bool))
    if not np.isfinite(prior.prior).all():
        prior = DepthPrior(inpaint_depth(prior.prior, ~np.isfinite(prior.prior)), prior.name)
    if known_depth is not None:
        known = np.isfinite(known_depth)
        name = f"{prior.name}; {int(known.sum())} px from the inserted object's hull depth"
        prior = DepthPrior(np.where(known, known_depth, prior.prior).astype(np.float32), name)
    write_npy(npy, prior.prior)
    write_text(meta, json.dumps({"name": prior.name, "view": k, "is_disparity": prior.is_disparity}))
    return prior


def _scene_targets(scene: Scene, targets: Sequence[np.ndarray], train_idx: Sequence[int]) -> list[np.ndarray]:
    """Targets per training view: `targets` aligned with the scene's views or with `train_idx`."""
    if len(targets) == len(scene.cameras):
        return [np.asarray(targets[i], np.float32) for i in train_idx]
    if len(targets) == len(train_idx):
        return [np.asarray(t, np.float32) for t in targets]
    raise ValueError(
        f"{len(targets)} targets: give one per scene view ({len(scene.cameras)}) or per training view "
        f"({len(train_idx)})"
    )


def run_refgs(
    scene: Scene,
    targets: list[np.ndarray],
    out_dir: Path,
    cfg: RefGSConfig,
    *,
    budget_minutes: float | None,
    iters: int | None,
    max_seconds: float = 0.0,
    device: DeviceLike = None,
    seed: int = 0,
    backend: str = "opencl",
    gs_depth: np.ndarray | None = None,
    ckpt_every: int = 500,
    callback: Callable[[Trainer, int], None] | None = None,
    seed_points: tuple[np.ndarray, np.ndarray] | None = None,
    known_depth: np.ndarray | None = None,
    object_masks: Sequence[np.ndarray] | None = None,
    exclude: Sequence[np.ndarray | None] | None = None,
    gaussians_per_pixel: float | None = None,
    schedule_iters: int | None = None,
    replan_seconds: float | None = None,
) -> dict[str, Any]:
    """Run (or continue) the Ref-GS stage; see the module doc for what lands in `out_dir`.

    Args:
        scene: a loaded `Scene` (cameras, images, masks [H, W] bool, points, train_idx, priors).
        targets: the initial inpaints I^_n [H, W, 3] float in [0, 1], one per scene view (as
            `coin_cl.scene.splits.inpainted_targets`) or one per training view.
        cfg: Ref-GS switches; its `seed`, where not None, wins over `seed`.
        budget_minutes / iters: schedule length (module doc). max_seconds: with `iters`, a safety
            cap on training seconds (0: none; the pipeline's budget plan sets it, logged when hit).
        device: OpenCL device for the renders; backend: 'opencl' or 'torch'.
        gs_depth: [H, W] depth of a GS trained on the unmasked scene for the reference view (used
            when the scene ships no depth prior; otherwise a short one is trained here).
        ckpt_every: steps between checkpoints; callback: the trainer's per-step callback.
        seed_points: (points [M, 3], colours [M, 3]) added to the initial points after the pruning
            (an inserted object's lift, `coin_cl.pipeline.insert`: it lies inside the masks, where
            pruning would remove it).
        known_depth: [H, W] camera z of the reference known from elsewhere (NaN where not; the
            inserted object's hull depth): replaces the depth prior there, and the dataset's
            inpainted disparity (made for removal) is then not used.
        object_masks: [H, W] bool per scene view, the removed object's masks: the SfM points are
            pruned by them and the background depth term holds the depth in them (default the
            scene's masks; the pipeline passes the input masks when refined masks narrow what is
            inpainted).
        exclude: [H, W] bool or None per scene view, pixels left out of the photometric loss (the
            observed part of a refined mask with `CoInConfig.observed` "captures": other views'
            captures teach it, as in masked reconstruction); default none.
        gaussians_per_pixel: the anchor-growth cap in neural Gaussians per training pixel
            (`ScaffoldStrategy.gaussians_per_pixel`; 0: none); None: the strategy's default.
        schedule_iters: the steps the learning-rate decay and the anchor growth are laid out over
            (>= the run's steps; None: the run's): a pipeline whose next stage trains the same model
            on (TE-D's fine-tune) passes both stages' steps, so that the two run one schedule.
        replan_seconds: with `iters`, the seconds the stage is planned to take from the call on:
            before training, `PROBE_STEPS` steps of the same model on a copy measure this machine
            and `iters` is planned again from them (`budget.refgs_steps_from_rate`); the decision
            is recorded in stage.json, and a rerun with the same `iters` keeps it. None: `iters`.
    Returns:
        JSON-able dict: output paths, reference, prior name, n_removed, steps, minutes, weights.
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seed = seed if cfg.seed is None else int(cfg.seed)
    cfg = replace(cfg, seed=seed)
    train_idx = list(scene.train_idx) or list(range(len(scene.cameras)))
    stage_json = out / STAGE_JSON
    prev_stage = parse_optional(stage_json, REFGS_STAGE, run_folder_fix(stage_json, "Ref-GS starts over"))
    if iters is None and budget_minutes is not None and prev_stage is not None:
        n_iters = int(prev_stage["iters"])  # the first call's plan (a new probe would time a busier machine)
    else:
        probe = lambda: probe_seconds_per_step(scene, train_idx, device, seed)  # noqa: E731
        n_iters = standalone_steps("refgs", budget_minutes, iters, probe)
    # the steps after Ref-GS's own that its schedule spans (TE-D's, when it continues it)
    extra = 0 if schedule_iters is None else max(0, int(schedule_iters) - n_iters)
    prev = prev_stage or {}
    replan = prev.get("replan")
    # the first call's decision (`replan_seconds`), kept when its record holds together
    if (
        isinstance(replan, dict)
        and replan.get("request") == n_iters
        and replan.get("steps") == prev.get("iters")
    ):
        n_iters = int(prev["iters"])
    else:
        replan = None
        if (out / "gs" / "ckpt.pt").is_file() and prev_stage is not None and prev_stage["iters"] != n_iters:
            log.warning("resuming a run planned for %d steps; ignoring the new request of %d",
                        prev_stage["iters"], n_iters)  # fmt: skip
            n_iters = int(prev_stage["iters"])
    # Write the plan before training so an interrupted run resumes with the same schedule.
    write_text(out / STAGE_JSON, json.dumps({**(prev_stage or {}), "iters": n_iters}, indent=1))

    # Reference view (scene index k, trainer index kt).
    k = choose_reference(scene, train_idx=train_idx, ref=cfg.ref)
    kt = train_idx.index(k)
    masks = [np.asarray(scene.masks[i], bool) for i in train_idx]
    # The object's masks: the pruning vote and the background depth term (refined masks, the unseen
    # core, hold the object in too few views for the vote: on the demo room they kept 611 of its
    # 1083 SfM points, which seeded Gaussians where it stood).
    obj = masks if object_masks is None else [np.asarray(object_masks[i], bool) for i in train_idx]
    inp = _scene_targets(scene, targets, train_idx)
    tgt = [composite_targets(t, np.asarray(scene.images[i], np.float32), m) if cfg.composite else t
           for t, i, m in zip(inp, train_idx, masks, strict=True)]  # fmt: skip
    views = []
    for j, i in enumerate(train_idx):
        cam = Camera.from_any(scene.cameras[i], name=str(i))
        ex = None if exclude is None or exclude[i] is None else torch.as_tensor(np.asarray(exclude[i], bool))
        views.append(View(cam, torch.as_tensor(np.ascontiguousarray(tgt[j][..., :3])), ex))

    # Points: pruned inside the object's masks before the anchors are built.
    pts, cols = init_points(scene, views)
    n_removed = 0
    if cfg.prune_points:
        pr = prune_points_in_masks(
            pts, [v.camera for v in views], obj, cfg.prune_min_fraction, cfg.prune_min_views
        )
        pts, cols, n_removed = pr.points, (None if cols is None else cols[pr.keep]), pr.n_removed
        log.info("pruned %d of %d SfM points inside the masks", n_removed, n_removed + len(pts))
    if seed_points is not None and len(seed_points[0]):
        sp, sc = (np.asarray(a, np.float32) for a in seed_points)
        pts = np.concatenate([pts, sp])
        cols = None if cols is None else np.concatenate([cols, sc])
        log.info("%d seed points added after pruning", len(sp))
    if len(pts) < MIN_POINTS:
        src = scene.meta.get("points_file", f"the sparse points of scene {scene.path}")
        raise ValueError(
            f"{src}: only {len(pts)} of its {len(scene.points)} sparse points are left outside the "
            f"object's masks ({n_removed} fell inside), {MIN_POINTS} are needed to seed the Gaussians; "
            "check that the masks cover only the object, or make a denser point cloud (`coin-cl "
            "prepare` on the photos)"
        )

    prior = None
    if cfg.depth_loss:
        prior = _depth_prior(
            scene,
            train_idx,
            k,
            n_iters,
            seed,
            backend,
            device,
            gs_depth,
            out,
            cfg.depth_prior_iters,
            known_depth,
        )
        log.info("reference depth prior: %s", prior.name)

    bg = None
    if cfg.bg_depth:
        bg = background_depths(
            [v.camera for v in views], obj, np.asarray(scene.points), planes=cfg.bg_depth_planes
        )
        _save_bg_depths(out / "bg_depths", scene, train_idx, bg)
        log.info(
            "background depth held in the masks of %d of %d views", sum(d is not None for d in bg), len(bg)
        )
    cap_seconds = 60.0 * budget_minutes if budget_minutes and iters is None else max_seconds

    def trainer(n: int, folder: Path | None, cb: Callable[[Trainer, int], None] | None) -> Trainer:
        mcfg = scaled_model_config("scaffold", n + extra)
        model = build_model("scaffold", pts, cols, scene_extent([v.camera for v in views]), seed, mcfg)
        model.device = device
        terms = refgs_terms(cfg, kt, masks, n, feat_dim=mcfg.feat_dim,
                            depth_prior=None if prior is None else prior.prior,
                            depth_is_disparity=bool(prior is not None and prior.is_disparity),
                            bg_depths=bg)  # fmt: skip
        tcfg = TrainConfig(model="scaffold", iters=n, backend=backend, seed=seed, ckpt_every=ckpt_every,
                           max_seconds=cap_seconds, progress=folder is not None,
                           log_every=max(1, min(50, n // 20)), aux_grad_ratio=cfg.aux_grad_ratio)  # fmt: skip
        strategy = scaled_strategy("scaffold", n + extra)
        if gaussians_per_pixel is not None:
            strategy = replace(strategy, gaussians_per_pixel=float(gaussians_per_pixel))
        if cfg.growth_over_initial > 1.0:  # from the model as built from the points, the same on a resume
            strategy = replace(strategy, min_cap=int(cfg.growth_over_initial * model.n_primitives))
        return Trainer(model, views, [], tcfg, folder, cb, strategy=strategy, terms=terms)

    if replan_seconds is not None and replan is None and not (out / "gs" / "ckpt.pt").is_file():
        replan = _replan(trainer, n_iters, replan_seconds - (time.perf_counter() - t_start))
        gc.collect()  # the timed copy's model, before the one that trains is built beside it
        n_iters = replan["steps"]
        write_text(out / STAGE_JSON, json.dumps({"iters": n_iters, "replan": replan}, indent=1))
    span = n_iters + extra
    tr = trainer(n_iters, out / "gs", callback)
    resumed = tr.ckpt_path is not None and tr.ckpt_path.is_file()
    if resumed:
        tr.load_checkpoint()
        saved = tr.log.get("refgs", {}).get("config")
        if saved is not None and saved != cfg.to_dict():
            log.warning(
                "resuming with a different RefGSConfig than the checkpoint's: %s vs %s", cfg.to_dict(), saved
            )
        log.info("Ref-GS resumed at step %d", tr.step)
    tr.log["refgs"] = {
        "config": cfg.to_dict(),
        "reference": {"index": k, "train_index": kt, "name": scene.cameras[k].name, "rule": "--ref" if
                      cfg.ref is not None else "largest, most central mask (reference_score)"},
        "depth_prior": None if prior is None else prior.name,
        "n_removed": n_removed,
        "n_points": int(len(pts)),
        "iters": n_iters,
        "schedule_iters": span,
        "replan": replan,
    }  # fmt: skip
    t0 = time.perf_counter()
    res = tr.train()
    weights = adaptive_weights_of(tr.terms)
    assert weights is not None  # refgs_terms always builds the weight source
    tr.log["view_weights"] = {
        "keys": "trainer view index (refgs.reference.train_index is the reference)",
        "history": weights.history,
        "summary": {str(v): s for v, s in weights.summary().items()},
    }
    tr.log["refgs"]["terms"] = {
        t.name: t.state_dict() for t in tr.terms if t.name in ("ref_depth", "bg_depth")
    }
    for t in tr.terms:
        if t.name == "attention":
            tr.log["refgs"]["attention"] = {"applied": t.n_applied, "skipped": t.n_skipped}
    tr.save_log()

    paths = _write_outputs(tr, scene, train_idx, k, kt, masks, out, backend)
    result = {
        "out_dir": str(out),
        **paths,
        "reference": {"index": k, "name": scene.cameras[k].name},
        "depth_prior": None if prior is None else prior.name,
        "n_removed": n_removed,
        "iters": n_iters,
        "steps": res["step"],
        "train_minutes": res["train_seconds"] / 60,
        # a step's cost once the model has grown: TE-D's steps are costed from it
        "late_seconds_per_step": late_step_seconds(tr.log["train"]),
        "wall_minutes_this_call": (time.perf_counter() - t0) / 60,
        "resumed": resumed,
        "n_primitives": res["n"],
        "mean_weight": {str(v): s["mean_weight"] for v, s in weights.summary().items()},
        "replan": tr.log["refgs"]["replan"],
        "config": cfg.to_dict(),
    }
    write_text(out / STAGE_JSON, json.dumps(result, indent=1))
    return result


def _replan(
    trainer: Callable[[int, Path | None, None], Trainer], request: int, seconds: float
) -> dict[str, Any]:
    """Ref-GS's count for `seconds` of training, planned from `PROBE_STEPS` steps of a copy of its
    model (`trainer(request, None, None)`, thrown away) and the growth its size cap allows
    (`budget.refgs_steps_from_rate`); logged. The record stage.json keeps: {"request", "steps",
    "first_seconds_per_step", "mean_seconds_per_step", "size", "size_limit", "seconds"}."""
    seconds = max(0.0, seconds)  # the stage already spent its time: the floor's steps
    tr = trainer(request, None, None)

    def step() -> None:
        tr.train_step()
        tr.step += 1

    size = tr.model.n_primitives
    limit = int(tr.strategy.size_limit(tr.model).get("neural_gaussians", 0))
    first = median_step_seconds(step, PROBE_STEPS, PROBE_WARMUP)
    steps, mean = refgs_steps_from_rate(seconds, first, size, limit)
    log.info("Ref-GS: %d steps in its %.1f min left (its first steps %.3f s each at %d primitives, "
             "growth to %d allowed: %.3f s/step on average; the plan's count was %d)", steps,
             seconds / 60, first, size, limit, mean, request)  # fmt: skip
    return {"request": request, "steps": steps, "first_seconds_per_step": first,
            "mean_seconds_per_step": mean, "size": size, "size_limit": limit, "seconds": seconds}  # fmt: skip


def _save_bg_depths(
    folder: Path, scene: Scene, train_idx: Sequence[int], bg: Sequence[np.ndarray | None]
) -> None:
    folder.mkdir(exist_ok=True)
    for i, d in zip(train_idx, bg, strict=True):
        if d is not None:
            write_npy(folder / f"{view_stem(scene.cameras[i].name, i)}.npy", d)


def read_bg_depths(folder: Path, scene: Scene, train_idx: Sequence[int]) -> list[np.ndarray | None]:
    """The D_bg a Ref-GS run saved (`bg_depths/`), per training view (None where it saved none)."""
    out = []
    for i in train_idx:
        p = Path(folder) / f"{view_stem(scene.cameras[i].name, i)}.npy"
        out.append(np.load(p) if p.is_file() else None)
    return out


def _write_outputs(tr: Trainer, scene: Scene, train_idx: Sequence[int], k: int, kt: int,
                   masks: Sequence[np.ndarray], out: Path, backend: str) -> dict[str, Any]:  # fmt: skip
    """Renders, depths and alphas of every training view, and P_k."""
    from coin_cl.scene.ply import write_points_ply

    rdir, ddir, adir = out / "renders", out / "depths", out / "alphas"
    for d in (rdir, ddir, adir):
        d.mkdir(exist_ok=True)
    ref = None
    for j, (v, i) in enumerate(zip(tr.train_views, train_idx, strict=True)):
        with torch.no_grad():
            r = tr.model.render(
                v.camera, tr.step, backend=backend, background=tr.background, return_depth=True
            )
        img = r.image.clamp(0, 1).numpy()
        depth = r.depth.numpy().astype(np.float32)
        alpha = r.alpha.numpy().astype(np.float32)
        stem = view_stem(scene.cameras[i].name, i)
        write_png(rdir / f"{stem}.png", img)
        write_npy(ddir / f"{stem}.npy", depth)
        write_npy(adir / f"{stem}.npy", alpha)
        if j == kt:
            ref = (img, depth, alpha)
    assert ref is not None
    img, depth, alpha = ref
    m = masks[kt]
    margin = pk_margin_px(m)
    ys, xs = reference_pixels(depth, m, margin, alpha > 0.5)
    pts = reference_points(scene.cameras[k], depth, m, margin, alpha > 0.5)
    pk = out / "reference_points.ply"
    write_points_ply(pk, pts, img[ys, xs])
    return {
        "checkpoint": str(tr.ckpt_path),
        "log": str(out / "gs" / "log.json"),
        "renders": str(rdir),
        "depths": str(ddir),
        "alphas": str(adir),
        "reference_points": str(pk),
        "n_reference_points": int(len(pts)),
        "pk_margin_px": margin,
    }
