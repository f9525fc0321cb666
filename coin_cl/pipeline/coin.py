"""CoIn end to end: `inpaint(scene, ...)` runs the paper's four stages on the stage runner.

    0_scene    the scene with the chosen masks (seg / bbox / scribble), in coin-cl's own layout
    1_inpaint  initial 2D inpaints I^_n                                  (paper 4.1; inpaint2d.py)
    2_refgs    Ref-GS: the reference-adaptive coarse Scaffold-GS          (paper 4.2; refgs.py)
    3_clg      consistency loss guidance: guided images I~_n             (paper 4.3; clg.py)
    4_ted      TE-D: fine-tune + texture-enhancing discriminator         (paper 4.4; ted.py)
    eval       renders of the test views, PLY, orbit GIF; metrics where ground truth exists

Every stage is a function from files to files under `out/` (see `runner`): rerunning skips what is
up to date, a killed run resumes, and `out/log.json` records each stage's settings, the models
used (Stable Diffusion 2 or the embedded scene prior, DINO or the analytic features, the depth
prior's source), timings and figures. The ablations of the paper's Table 4 are settings:
`skip=("refgs",)` trains the coarse stage without Ref-GS's pieces, `skip=("clg",)` / `("ted",)`
leave those stages out (the next stage then reads the one before), and `RefGSConfig` switches
adaptive weights, attention and the depth loss one by one.

Budget: `budget_minutes` is the run's wall-clock minutes, every stage included. The paper's
iteration counts (10k Ref-GS, 200 CLG steps, 10k + 10k TE-D) are far beyond 2 CPU cores;
`coin_cl.pipeline.budget` picks the working resolution from the image size, subtracts the fixed
stages' estimated cost and turns the rest into GS step counts with timing probes on the machine at
hand, recorded in `out/plan.json`; each GS stage is planned again when it is reached from the
seconds the stages before it recorded, so a rerun (or a resumed run) uses the same counts.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from coin_cl.opencv_contrib import require_contrib
from coin_cl.pipeline.budget import MAX_WORK_PIXELS, PRIOR_MIN_SECONDS, working_resolution
from coin_cl.pipeline.coin_plan import clg_skip_reason, plan_for
from coin_cl.pipeline.config import STAGES, CoInConfig
from coin_cl.pipeline.eval_stage import stage_eval
from coin_cl.pipeline.inpaint2d import prior_key
from coin_cl.pipeline.inpaint2d import rerun_key as inpaint_key
from coin_cl.pipeline.lock import folder_lock
from coin_cl.pipeline.refine_masks import vote_ring
from coin_cl.pipeline.run_inputs import CaptureViews, RunInputs, capture_views
from coin_cl.pipeline.runner import Stage, check_output_folder, jsonable, run_stages
from coin_cl.pipeline.schedule import refgs_schedule_span, stage_schedule
from coin_cl.pipeline.stages import (
    carves,
    load_model,
    refgs_settings,
    seeds_background,
    stage_clg_adapter,
    stage_inpaint,
    stage_refgs,
    stage_refine,
    stage_scene,
    stage_ted,
)

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.gs.base import Model
    from coin_cl.scene import Scene

log = logging.getLogger(__name__)

# Share of the masks that other views must see (estimated) for "auto" to choose refined masks:
# measured 0.16 on the forward-facing SPIn-NeRF scene, 0.65 / 0.78 / 0.82 on the synthetic room's 90 /
# 180 / 360-degree arcs (exact: 0.78 / 0.83 / 0.83; tests/test_carve.py).
AUTO_REFINE_SHARE = 0.3

__all__ = ["STAGES", "CoInConfig", "CoInResult", "inpaint", "summary"]


@dataclass
class CoInResult:
    """out: the run folder; ply: the final Gaussians (standard 3DGS layout); renders: test-view
    images; metrics: the evaluation document (None without ground truth); model: the final model;
    stages: the runner's records."""

    out: Path
    ply: Path | None
    renders: Path | None
    metrics: dict | None
    model: Model
    stages: dict[str, dict]


def scene_id(scene: Scene) -> dict[str, Any]:
    """What names a scene for the output folder check: its view count, names and a hash of its
    pixels as captured (before any resizing). Not its path: the same folder under another spelling
    (a symlink, `./`) is the same scene, and another resolution of it is the same scene too (its
    stages rerun, since the resolution is in their settings)."""
    h = hashlib.sha256()
    for img in scene.images:
        h.update(np.ascontiguousarray(img[::7, ::7]).tobytes())
    return {
        "n_views": len(scene),
        "names": hashlib.sha256("/".join(c.name for c in scene.cameras).encode()).hexdigest()[:16],
        "pixels": h.hexdigest()[:16],
    }


def mask_dilation(scene: Scene, cfg: CoInConfig) -> int:
    """The training masks' dilation (iterations of a 5x5 kernel): `cfg.mask_dilate`, or when None
    0 for a scene that declares its masks exact (`scene.meta["masks"]`, the synthetic rooms), else
    `scene.masks.auto_dilation` of the working size (logged)."""
    from coin_cl.scene.masks import MASK_RING_SHARE, auto_dilation

    if cfg.mask_dilate is not None:
        if cfg.mask_dilate < 0:
            raise ValueError(f"CoInConfig.mask_dilate must be >= 0 or None (auto), got {cfg.mask_dilate}")
        return int(cfg.mask_dilate)
    if scene.meta.get("masks") == "exact":
        log.info("training masks kept as given: the scene declares them exact (scene_info.json); "
                 "--mask-dilate N overrides")  # fmt: skip
        return 0
    cam = scene.cameras[scene.train_idx[0]]
    n = auto_dilation(cam.width, cam.height)
    log.info("training masks dilated by %d px (%.1f %% of the longer side, as SPIn-NeRF's; --mask-dilate "
             "overrides)", 2 * n, 100 * MASK_RING_SHARE)  # fmt: skip
    return n


def _train_masks(scene: Scene, cfg: CoInConfig) -> list[np.ndarray]:
    from coin_cl.scene.masks import derive_mask

    dilate = mask_dilation(scene, cfg)
    out = []
    for i, m in enumerate(scene.masks):
        if i in scene.train_idx and m.any():
            out.append(derive_mask(m, cfg.mask_kind, seed=cfg.seed + i, dilate=dilate))
        else:
            out.append(np.asarray(m, bool))
    return out


def _stage_names(force: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Stage folder names from `force` entries: a folder name ("3_clg") or its short name ("clg");
    anything else is an error listing the names (a typo must not be ignored silently)."""
    short = {s.split("_", 1)[1]: s for s in STAGES if "_" in s} | {"eval": "eval"}
    out = []
    for f in force:
        name = f if f in STAGES else short.get(f)
        if name is None:
            names = f"{', '.join(STAGES)} (or {', '.join(short)})"
            raise ValueError(f"cannot force {f!r}: the stages are {names}")
        out.append(name)
    return tuple(out)


def inpaint(
    scene: Scene | str | Path,
    out: str | Path,
    *,
    mask_kind: str | None = None,
    masks: list[np.ndarray] | None = None,
    reference: int | str | None = None,
    prompt: str | None = None,
    budget: float | None = None,
    config: CoInConfig | None = None,
    device: DeviceLike = None,
    force: tuple[str, ...] = (),
    edited_ref: str | Path | np.ndarray | None = None,
) -> CoInResult:
    """Remove the masked object in a captured scene, or insert one: from a text prompt (SD2
    weights) or from one view edited by the user (`edited_ref`, no weights needed).

    Args:
        scene: a `coin_cl.scene.Scene` or a folder `load_scene` reads.
        out: the run folder (created; a rerun resumes and skips what is up to date).
        mask_kind: "seg" | "bbox" | "scribble" (default `config.mask_kind`).
        masks: per-view (H, W) bool arrays replacing the scene's masks.
        reference: the reference view: an index, or a view name (with or without extension); a
            name that exists wins over an index; default: chosen by rule.
        prompt: text for insertion (needs Stable Diffusion 2 weights: `config.sd_path`).
        budget: the run's wall-clock minutes, every stage included (default
            `config.budget_minutes`); one this machine cannot fit raises
            `budget.BudgetTooSmall` (a ValueError naming the minimum) before any stage runs.
        config: everything else (`CoInConfig`). device: the OpenCL device (Runtime or name).
        edited_ref: the reference view edited in a 2D tool (a path, or (H, W, 3) uint8 / float in
            [0, 1]) at the captured or the run's resolution. Without masks of the object in the
            other views it is stood on the surface under it and their regions are derived
            (`coin_cl.pipeline.insert_geometry`); with masks covering it in every view it is lifted
            by their visual hull (`InsertConfig.regions`). Its view is `reference` or, without one,
            the training view it matches outside the mask (`coin_cl.pipeline.insert`).
    Returns:
        `CoInResult` (paths, metrics, final model).
    """
    from coin_cl.scene import load_scene

    cfg = config or CoInConfig()
    if isinstance(masks, str):
        raise TypeError(f"masks= takes per-view arrays; for the mask kind use mask_kind={masks!r}")
    if mask_kind is not None:
        cfg = replace(cfg, mask_kind=mask_kind)
    if reference is not None:
        cfg = replace(cfg, ref=reference)
    if prompt is not None:
        cfg = replace(cfg, prompt=prompt)
    if budget is not None:
        cfg = replace(cfg, budget_minutes=float(budget))
    if device is not None:
        cfg = replace(cfg, device=device if isinstance(device, str) else getattr(device, "name", None))
    if isinstance(scene, str | Path):
        from coin_cl.pipeline.memory import check_scene_files

        pre = check_scene_files(scene, cfg.resolution)  # headers only: before any image is decoded
        log.info("memory before loading: about %.1f GiB to decode the images, %.1f GiB for the run "
                 "without its points", pre.parts["decode"] / 2**30, pre.bytes / 2**30)  # fmt: skip
        scene = load_scene(scene)
    if isinstance(masks, list):
        if len(masks) != len(scene):
            raise ValueError(f"masks has {len(masks)} entries for a scene of {len(scene)} views")
        for i, m in enumerate(masks):
            if tuple(np.shape(m)) != tuple(scene.masks[i].shape):
                raise ValueError(f"mask {i} has shape {np.shape(m)}, the view is {scene.masks[i].shape}")
        scene = replace(scene, masks=[np.asarray(m, bool) for m in masks])
    if edited_ref is not None and not isinstance(edited_ref, np.ndarray):
        cfg = replace(cfg, edited_ref=str(edited_ref))
    if cfg.sd_path is None:
        from coin_cl.diffusion.sd2 import resolve_sd2_path

        env = resolve_sd2_path(None)  # COIN_SD2_PATH
        cfg = replace(cfg, sd_path=None if env is None else str(env))
    insertion = bool(cfg.prompt or edited_ref is not None or cfg.edited_ref)
    if cfg.inpaint_region == "auto" and insertion:
        cfg = replace(cfg, inpaint_region="input")  # insertion: nothing to recover from other views
    if cfg.ted.rates == "auto":  # TEDConfig.rates: insertion restarts (a continued fit let the object leak)
        cfg = replace(cfg, ted=replace(cfg.ted, rates="restart" if insertion else "continue"))
    if cfg.inpaint_region == "refined" and insertion:
        raise ValueError(
            "refined masks are for removal: they cannot be combined with a prompt or --edited-ref"
        )
    if cfg.prompt and (edited_ref is not None or cfg.edited_ref):
        raise ValueError("give either a text prompt or an edited reference view (--edited-ref), not both")
    if cfg.prompt and not cfg.sd_path:
        raise ValueError(
            "a text prompt needs Stable Diffusion 2 inpainting weights: pass sd_path / --sd-path or set "
            "COIN_SD2_PATH to a diffusers-format folder (the embedded scene prior has no text input)"
        )
    captured = scene_id(scene)
    if cfg.resolution is None:
        cam0 = scene.cameras[scene.train_idx[0] if scene.train_idx else 0]
        cfg = replace(cfg, resolution=working_resolution(cam0.width, cam0.height))
        log.info(
            "working resolution %.4g (%dx%d -> %dx%d): the largest 1/n scale with at most %d pixels a view "
            "(coin_cl.pipeline.budget; --resolution overrides)", cfg.resolution, cam0.width, cam0.height,
            round(cam0.width * cfg.resolution), round(cam0.height * cfg.resolution), MAX_WORK_PIXELS,
        )  # fmt: skip
    capture = None
    if cfg.resolution != 1.0:
        capture = capture_views(scene)
        scene = scene.resized(cfg.resolution)
    if not any(scene.masks[i].any() for i in scene.train_idx) and edited_ref is None and not cfg.edited_ref:
        raise ValueError(
            f"scene {scene.path} has no training view with a mask: nothing to inpaint "
            "(give masks, e.g. a label/ or masks/ folder)"
        )
    check_points(scene)
    require_contrib()  # before minutes of work, not at the first call of a missing module
    from coin_cl.pipeline.memory import check_memory

    # check_memory refuses a scene that cannot fit, before any stage runs
    log.info("memory: about %.1f GiB needed at most", check_memory(scene).bytes / 2**30)
    edited = None
    if edited_ref is not None or cfg.edited_ref:
        from coin_cl.pipeline.insert import load_edited

        src = edited_ref if edited_ref is not None else cfg.edited_ref
        cam = scene.cameras[scene.train_idx[0]]
        full = (round(cam.width / cfg.resolution), round(cam.height / cfg.resolution))
        edited = load_edited(src, (cam.width, cam.height), full if cfg.resolution != 1.0 else None)
    out = Path(out)
    force = _stage_names(force)
    # Locked before anything is written (plan.json included): a second run on the folder is refused
    # before it can touch the first's files.
    with folder_lock(out):
        check_output_folder(out, captured)
        return _run(scene, out, cfg, force, edited, capture)


def check_points(scene: Scene) -> None:
    """Refuse a scene without enough finite sparse points to seed the Gaussians (before any stage):
    one line naming its points file and what to do."""
    from coin_cl.pipeline.refgs import MIN_POINTS

    pts = np.asarray(scene.points, np.float64).reshape(-1, 3)
    n = int(np.isfinite(pts).all(axis=1).sum())
    if n < MIN_POINTS or n < len(pts):
        src = scene.meta.get("points_file", f"the sparse points of scene {scene.path}")
        what = f"has {len(pts) - n} points with NaN or Inf" if n < len(pts) else f"has only {n} sparse points"
        raise ValueError(
            f"{src}: {what} ({MIN_POINTS} finite ones are needed to seed the Gaussians); make the "
            "scene's point cloud again: `coin-cl prepare PHOTOS --out SCENE` (or COLMAP's mapper)"
        )


def _choose_region(scene: Scene, masks: list[np.ndarray], cfg: CoInConfig) -> str:
    """'refined' when other views see at least AUTO_REFINE_SHARE of the masks (a cheap estimate from
    the cameras and the sparse points, seconds; `coin_cl.gs.carve.observed_share`), else 'input'."""
    from coin_cl.gs.carve import build_carve, observed_share

    train = list(scene.train_idx)
    try:
        vol = build_carve([scene.cameras[i] for i in train], [masks[i] for i in train],
                          np.asarray(scene.points), cfg.carve_cfg)  # fmt: skip
    except ValueError as exc:
        log.info("inpaint region: input (no visibility estimate: %s)", exc)
        return "input"
    share = observed_share(vol)[0] if vol is not None else 0.0
    region = "refined" if share >= AUTO_REFINE_SHARE else "input"
    log.info(
        "inpaint region: %s (other views see an estimated %.0f%% of the masks; refined from %.0f%%; "
        "--inpaint-region overrides)", region, 100 * share, 100 * AUTO_REFINE_SHARE,
    )  # fmt: skip
    return region


def _run(
    scene: Scene,
    out: Path,
    cfg: CoInConfig,
    force: tuple[str, ...],
    edited: np.ndarray | None = None,
    capture: CaptureViews | None = None,
) -> CoInResult:
    from coin_cl.pipeline.reference import choose_reference

    cfg = replace(cfg, mask_dilate=mask_dilation(scene, cfg))  # resolved once: the stage keys hold it
    masks = _train_masks(scene, cfg)
    if cfg.inpaint_region == "auto":
        cfg = replace(cfg, inpaint_region=_choose_region(scene, masks, cfg))
    train = list(scene.train_idx)
    if edited is not None:  # before any stage; a one-photo insertion's masks are derived here
        from coin_cl.pipeline.insert import prepare_edit

        ref, masks, icfg = prepare_edit(edited, scene, masks, train, cfg.ref, cfg.insert,
                                        cfg.edited_ref or "the edited reference")  # fmt: skip
        cfg = replace(cfg, insert=icfg)
    else:
        ref = choose_reference(masks, scene.cameras, train_idx=train, ref=cfg.ref)
    cam = scene.cameras[train[0]]
    plan = plan_for(scene, out, cfg, train, edited)
    if plan.prior_seconds < PRIOR_MIN_SECONDS and not cfg.sd_path:
        log.warning(
            "the scene prior gets %.0f s of training (prior_seconds); below %.0f s it is measured to be "
            "untrained on 2 cores and its fills are noise: use this for smoke tests only",
            plan.prior_seconds, PRIOR_MIN_SECONDS,
        )  # fmt: skip
    # Ref-GS trains around the pipeline's reference, the one CLG warps from: left to its own rule it
    # would choose again from the masks it is given (refined masks, insertion footprints), or ignore
    # --ref, and P_k would then come from another view than CLG's camera k.
    run = RunInputs(out=out, scene=scene, masks=masks, ref=ref, cfg=cfg, plan=plan,
                    refgs_cfg=refgs_settings(cfg, ref, edited), edited=edited, capture=capture)  # fmt: skip
    log.info(
        "CoIn: %d training views at %dx%d (%d with a mask), reference view %d (%s), %s masks; %s",
        len(train), cam.width, cam.height, sum(masks[i].any() for i in train), ref, scene.cameras[ref].name,
        cfg.mask_kind, plan.describe(),
    )  # fmt: skip
    records = run_stages(out, coin_stages(run), run, force)
    final = final_stage(cfg)
    ev = records["eval"].get("result", {})
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME

    model = load_model(out / final, CKPT_NAME, model_from_state)
    return CoInResult(
        out=out,
        ply=out / "eval" / "point_cloud.ply",
        renders=out / "eval" / "renders",
        metrics=ev.get("metrics"),
        model=model,
        stages=records,
    )


def final_stage(cfg: CoInConfig) -> str:
    """The stage whose model is the result: TE-D's, or Ref-GS's when TE-D is skipped."""
    return "2_refgs" if "ted" in cfg.skip else "4_ted"


def coin_stages(run: RunInputs) -> list[Stage[RunInputs]]:
    """The stage graph of a CoIn run: each stage's function, the stages it reads and its key's
    settings (everything its output depends on besides what it reads). Building it computes
    nothing and writes nothing; the GS stages' settings are functions the runner calls when it
    reaches them (their counts are planned again from what the stages before them recorded:
    `schedule.stage_schedule`)."""
    cfg, plan, ref, edited = run.cfg, run.plan, run.ref, run.edited
    cam = run.scene.cameras[run.scene.train_idx[0]]
    base = {"seed": cfg.seed, "resolution": cfg.resolution, "mask": cfg.mask_kind, "dilate": cfg.mask_dilate}
    # The edited image's content (not its path) decides whether stage 1 and what follows rerun.
    edit = None if edited is None else {"sha256": hashlib.sha256(edited.tobytes()).hexdigest(),
                                        "ref": ref, "cfg": jsonable(cfg.insert)}  # fmt: skip
    refined = cfg.inpaint_region == "refined"
    clg_cfg = cfg.clg_settings()  # the defaults in the key too: a changed default reruns CLG
    clg_skip = clg_skip_reason(cfg, edited)
    r = ["0_refine"] if refined else []  # read by every stage that sees the views' masks
    # only "captures" enters the keys: "target" runs made before the option keep their stages
    observed_key = {"observed": cfg.observed} if refined and cfg.observed != "target" else {}
    ring = vote_ring(cam.width, cam.height, cfg.mask_dilate)  # 0 with the default dilation

    # The GS stages' counts are planned again when each is reached, from the seconds the stages
    # before it recorded (`schedule.stage_schedule`): their settings are functions the runner calls then.
    def steps(stage: str) -> dict[str, int]:
        return stage_schedule(run.out, plan, stage, cfg.budget_minutes).steps

    def ted_key() -> dict[str, Any]:
        it = steps("4_ted")
        return {"cfg": jsonable(cfg.ted), "iters": [it["ted_finetune"], it["ted_adversarial"]],
                "seed": cfg.seed, **observed_key}  # fmt: skip

    def refine_key() -> dict[str, Any]:
        # keyed by the fit's effective steps: a baseline that trains longer (the naive row at CoIn's
        # budget) but fixes the fit at CoIn's count reuses CoIn's split. Without a count of its own in
        # the plan (explicit counts), the fit takes Ref-GS's.
        n = (
            cfg.refine.iters
            if cfg.refine.iters is not None
            else steps("0_refine").get("refine", plan.steps["refgs"])
        )
        return {
            "cfg": jsonable(replace(cfg.refine, iters=None)),
            "iters": n,
            **({"vote_ring": ring} if ring else {}),
        }

    def refgs_key() -> dict[str, Any]:
        n = steps("2_refgs")["refgs"]
        return {"cfg": jsonable(run.refgs_cfg), "ref": ref, "iters": n,
                "schedule_iters": cfg.refgs_schedule_iters or refgs_schedule_span(
                    plan, n, "ted" not in cfg.skip and cfg.ted.rates == "continue"),
                "seed": cfg.seed,
                "carve": jsonable(cfg.carve_cfg) if carves(cfg, edited) else None,
                "seed_background": seeds_background(cfg, edited),
                "plain": "refgs" in cfg.skip, **observed_key}  # fmt: skip

    stages: list[Stage[RunInputs]] = [
        Stage("0_scene", stage_scene, settings=base),
        *([Stage("0_refine", stage_refine, ["0_scene"], refine_key)] if refined else []),
        Stage("1_inpaint", stage_inpaint, ["0_scene", *r],
              {**inpaint_key(cfg.inpaint2d), **prior_key(cfg.inpaint2d, plan.prior_seconds, plan.prior_steps),
               "seed": cfg.seed, "sd": cfg.sd_path, "prompt": cfg.prompt, "edited_ref": edit,
               **({"insert": jsonable(cfg.insert)} if cfg.prompt else {})}),
        Stage("2_refgs", stage_refgs, ["0_scene", *r, "1_inpaint"], refgs_key),
        Stage("3_clg", stage_clg_adapter, ["0_scene", *r, "1_inpaint", "2_refgs"],
              {"cfg": jsonable(clg_cfg), "ref": ref, "dino": cfg.dino_path, "seed": cfg.seed,
               "sd": cfg.sd_path, "prompt": cfg.prompt,
               **({"sd2_mode": cfg.inpaint2d.sd2_mode} if cfg.sd_path else {})},
              skip=clg_skip),
        Stage("4_ted", stage_ted,
              ["0_scene", *r, "1_inpaint", "2_refgs"] + ([] if clg_skip else ["3_clg"]),
              ted_key, skip="asked (--skip-stage ted)" if "ted" in cfg.skip else None),
    ]  # fmt: skip
    final = final_stage(cfg)
    stages.append(Stage("eval", stage_eval, ["0_scene", *r, final], {"final": final}))  # 0_refine: the split
    return stages


def summary(out: Path) -> dict:
    """The run log (`out/log.json`) as a dict."""
    return json.loads((Path(out) / "log.json").read_text())
