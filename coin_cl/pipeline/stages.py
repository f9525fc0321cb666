"""The CoIn stage functions (paper 4.1-4.4 and supplement C.2): each reads the folders of the stages
before it and writes its own; `coin_cl.pipeline.coin` builds the stage graph and the runner
(`coin_cl.pipeline.runner`) decides what runs. What every stage is given is `ctx.run`, the run's
`RunInputs` (`coin_cl.pipeline.run_inputs`): the scene, the input masks, the reference, the run's
`CoInConfig` and its `budget.Plan`.

    stage_scene    0_scene    the scene with the chosen masks, in coin-cl's own layout
    stage_refine   0_refine   refined masks (`refine_masks`), when the run takes them
    stage_inpaint  1_inpaint  initial 2D inpaints I^_n (`inpaint2d`), or an insertion's stage 1
    stage_refgs    2_refgs    Ref-GS (`pipeline.refgs`), with the optional carve (`gs.carve`)
    stage_clg_adapter 3_clg   CLG (`pipeline.clg`)
    stage_ted      4_ted      TE-D (`pipeline.ted`)
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coin_cl.pipeline.budget import CAP_FACTOR
from coin_cl.pipeline.inpaint2d import planned_config, read_inpaints, run_inpaint2d
from coin_cl.pipeline.models import resolve_sd2_mode, sd2_denoiser, sd2_on_cpu
from coin_cl.pipeline.runner import StageContext, jsonable
from coin_cl.pipeline.schedule import refgs_rate, stage_schedule, ted_schedule

if TYPE_CHECKING:
    from coin_cl.diffusion.sampling import Denoiser
    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.gs.terms import LossTerm
    from coin_cl.pipeline.config import CoInConfig
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
    from coin_cl.pipeline.run_inputs import RunInputs
    from coin_cl.scene import Scene

log = logging.getLogger(__name__)


def latest_ckpt(folder: Path, ckpt_name: str) -> Path:
    cands = sorted(folder.rglob(ckpt_name), key=lambda p: p.stat().st_mtime)
    if not cands:
        raise FileNotFoundError(f"no {ckpt_name} under {folder}")
    return cands[-1]


def load_model(folder: Path, ckpt_name: str, model_from_state):
    """The model of the newest `ckpt_name` under the stage folder `folder`, read without running
    code (`coin_cl.checkpoint`); a bad file is one line naming it and the stage to rerun."""
    from coin_cl.checkpoint import load_checkpoint, malformed

    path = latest_ckpt(folder, ckpt_name)
    remedy = f"rerun with --force {folder.name} to train it again"
    state = load_checkpoint(path, remedy)
    try:
        return model_from_state(state["model"])
    except (KeyError, TypeError, AttributeError, IndexError) as exc:
        raise malformed(path, exc, remedy) from None


def stage_scene(ctx: StageContext[RunInputs]) -> dict:
    from coin_cl.scene import save_scene

    scene, masks = ctx.run.scene, ctx.run.masks
    save_scene(replace(scene, masks=masks), ctx.out / "scene")
    empty = [scene.cameras[i].name for i in scene.train_idx if not masks[i].any()]
    if empty:
        ctx.note(f"{len(empty)} training views have no mask and are kept as captured: {empty[:5]}...")
    area = [float(masks[i].mean()) for i in scene.train_idx]
    return {"views": len(scene), "train": len(scene.train_idx), "test": len(scene.test_idx),
            "mask": ctx.run.cfg.mask_kind, "mean_mask_area": float(np.mean(area))}  # fmt: skip


def _scene_views(ctx: StageContext[RunInputs]) -> tuple[Scene, list[np.ndarray], list[int]]:
    """(scene, masks, training views) as the stage sees them: the input masks; with refined masks
    (stage 0_refine) M^rmv_n and the captures with R^rmv_n in the rest of the input mask; after an
    insertion's stage 1 the object's footprints F_n (`coin_cl.pipeline.insert`), which are the only
    pixels that change (the rest of the input mask is captured background)."""
    scene, masks = ctx.run.scene, ctx.run.masks
    if "0_refine" in ctx.inputs:
        from coin_cl.pipeline.refine_masks import read_refined

        images, masks = read_refined(scene, ctx.inputs["0_refine"], list(scene.train_idx), masks)
        scene = replace(scene, images=images)
    feet = ctx.inputs.get("1_inpaint", Path("-")) / "footprints"
    if ctx.name != "1_inpaint" and feet.is_dir():
        from coin_cl.scene.masks import read_mask

        masks = list(masks)
        for i in scene.train_idx:
            p = feet / (Path(scene.cameras[i].name).stem + ".png")
            masks[i] = read_mask(p, masks[i].shape)
    return scene, masks, list(scene.train_idx)


def stage_refine(ctx: StageContext[RunInputs]) -> dict:
    from coin_cl.pipeline.refine_masks import refine_masks
    from coin_cl.scene.masks import dilate_mask

    scene, masks = ctx.run.scene, ctx.run.masks
    cfg = ctx.run.cfg
    tests = [i for i in scene.test_idx if np.asarray(masks[i]).any()]  # their split: for the eval
    ring = ctx.settings.get("vote_ring", 0)
    vote = None
    if ring:
        log.info("refine masks: the removal vote on the training masks dilated %d px more (tighter than the "
                 "default ring: the vote needs the object's fringe inside every mask)", 2 * ring)  # fmt: skip
        vote = [dilate_mask(m, iterations=ring) if i in scene.train_idx else m for i, m in enumerate(masks)]
    res = refine_masks(scene, masks, list(scene.train_idx), ctx.out, cfg.refine, ctx.settings["iters"],
                       cfg.seed, cfg.device, also=tests, vote_masks=vote)  # fmt: skip
    ctx.note(f"refined masks: {res['refined_px']} of {res['input_px']} mask px left to inpaint "
             f"({res['refined_ratio']:.0%}); per view in 0_refine/areas.json")  # fmt: skip
    return res


def sd2_mode_for(cfg: CoInConfig, sd2: Denoiser, n_views: int) -> tuple[str, str]:
    """`resolve_sd2_mode` for a pipeline run: `CoInConfig` cfg (its inpaint2d.sd2_mode, stage 1's
    and CLG's step counts), the loaded SD2 denoiser, n_views masked training views."""
    from coin_cl.pipeline.clg_config import CLGConfig

    clg_steps = (cfg.clg or CLGConfig()).num_steps(sd2)
    steps = cfg.inpaint2d.inpaint.sampler_sd.num_steps
    return resolve_sd2_mode(cfg.inpaint2d.sd2_mode, n_views, steps, sd2_on_cpu(sd2), clg_steps)


def stage_inpaint(ctx: StageContext[RunInputs]) -> dict:
    scene, masks, train = _scene_views(ctx)
    cfg = ctx.run.cfg
    if ctx.run.edited is not None:
        from coin_cl.pipeline.insert import run_insert

        res = run_insert(scene, masks, train, ctx.run.ref, ctx.run.edited, ctx.out, cfg.insert,
                         cfg.device)  # fmt: skip
        ctx.note(f"initial images: {res['source']}; {res['views_without_object']} views without the object")
        return res
    cam = scene.cameras[train[0]]
    icfg = planned_config(cfg.inpaint2d, ctx.run.plan, cfg.seed, cam.width, cam.height)
    sd2, only, why = sd2_denoiser(cfg.sd_path), None, ""
    if cfg.prompt and cfg.insert.propagate and sd2 is not None:
        return _prompt_insert(ctx, scene, masks, train, sd2, icfg)
    if sd2 is not None:  # SD2 on every view, or on the reference only (SD2's CPU-practical mode)
        mode, why = sd2_mode_for(cfg, sd2, sum(bool(masks[i].any()) for i in train))
        ctx.note(why)
        only = [ctx.run.ref] if mode == "reference_only" else None
    # Undilated or refined masks end where the object does: a paste must not blend its outline back.
    # (Inpainted on the captures, the hole is the input mask, exact only when not dilated.)
    exact = cfg.mask_dilate == 0 or "0_refine" in ctx.inputs
    context = None
    if "0_refine" in ctx.inputs and icfg.context == "captures":
        context, exact = (ctx.run.scene.images, ctx.run.masks), cfg.mask_dilate == 0
        ctx.note("the unseen cores are filled from the captures around the whole input masks")
    res = run_inpaint2d(scene, masks, train, ctx.out, icfg, cfg.mask_kind, sd2=sd2, prompt=cfg.prompt,
                        sd2_views=only, sd2_why=why, exact_masks=exact, context=context)  # fmt: skip
    for s in res["sources"]:
        ctx.note(f"initial inpainting source: {s}")
    return res


def _prompt_insert(ctx: StageContext[RunInputs], scene: Scene, masks: list[np.ndarray], train: list[int],
                   sd2: Denoiser, icfg: Inpaint2DConfig) -> dict:  # fmt: skip
    """Stage 1 of an insertion from a text prompt: Stable Diffusion 2 draws the prompt into the
    reference's mask alone (`prompt/images/`), and that view is then an edited reference like a
    user's photo: lifted by the masks' visual hull and warped into every other view
    (`insert.run_insert`, regions "hull"), so the views agree by construction and SD2 runs once."""
    from coin_cl.pipeline.insert import edit_region, run_insert

    cfg, k = ctx.run.cfg, ctx.run.ref
    run_inpaint2d(scene, masks, [k], ctx.out / "prompt", icfg, cfg.mask_kind, sd2=sd2, prompt=cfg.prompt,
                  sd2_views=[k], sd2_why="a text insertion: SD2 draws the reference, the lift the rest",
                  exact_masks=cfg.mask_dilate == 0)  # fmt: skip
    edited = read_inpaints(scene, ctx.out / "prompt", [k])[k]
    icfg_ins = replace(cfg.insert, regions="hull")
    if not edit_region(edited, scene.images[k], masks[k], icfg_ins.edit_tol).any():
        raise ValueError(
            f"Stable Diffusion 2 drew nothing for the prompt {cfg.prompt!r} in view {scene.cameras[k].name} "
            f"(its fill equals the capture inside the mask): nothing to insert; reword the prompt, change "
            f"--seed, or give a larger mask there"
        )
    res = run_insert(scene, masks, train, k, edited, ctx.out, icfg_ins, cfg.device)
    ctx.note(f"the prompt drawn by Stable Diffusion 2 into the reference {scene.cameras[k].name}, then "
             f"{res['source']}; {res['views_without_object']} views without the object")  # fmt: skip
    return {**res, "sources": ["Stable Diffusion 2 inpainting (the reference), lifted"]}


def _targets(ctx: StageContext[RunInputs], folder: Path) -> dict[int, np.ndarray]:
    scene, masks, train = _scene_views(ctx)
    from coin_cl.gs.targets import composite_targets

    inp = read_inpaints(scene, folder, train)
    # Outside the mask the captured image is the truth (paper 5.1).
    return {i: composite_targets(inp[i], scene.images[i], masks[i]) for i in train}


def stage_refgs(ctx: StageContext[RunInputs]) -> dict:
    from coin_cl.pipeline.refgs import run_refgs

    scene, masks, train = _scene_views(ctx)
    cfg = ctx.run.cfg
    targets = _targets(ctx, ctx.inputs["1_inpaint"])
    rcfg = ctx.run.refgs_cfg
    if "refgs" in cfg.skip:
        from coin_cl.gs.refgs import RefGSConfig

        rcfg = RefGSConfig(
            adaptive_weights=False,
            feature_attention=False,
            depth_loss=False,
            prune_points=False,
            bg_depth=False,
            ref=ctx.run.ref,
            seed=rcfg.seed,
        )
        ctx.note("w/o Ref-GS: plain Scaffold-GS on the initial inpaints (ablation)")
    scene_m = replace(scene, masks=masks, ref_view=ctx.run.ref)
    full = [targets.get(i, scene.images[i]) for i in range(len(scene))]
    from coin_cl.pipeline.insert import read_lift

    # The count the stage's key holds, planned again from what the stages before recorded.
    sched = stage_schedule(ctx.run.out, ctx.run.plan, "2_refgs", cfg.budget_minutes)
    iters, cap = int(ctx.settings["iters"]), sched.caps.get("refgs", 0.0)
    ctx.note(f"Ref-GS: {iters} steps" + ("" if not cap else f", ~{cap / CAP_FACTOR / 60:.1f} min planned"
             f" (the count planned again from its first steps; stopped at {cap / 60:.1f} min if slower; "
             f"the probe's plan: {ctx.run.plan.steps['refgs']})"))  # fmt: skip
    lift = read_lift(ctx.inputs["1_inpaint"])
    # The object's volume is the input masks', also when refined masks narrow what is inpainted (the
    # carve here, the pruning vote and the background depth in run_refgs's object_masks).
    attach, bg = _background_hook(ctx, ctx.run.scene, ctx.run.masks, train)
    seed_points = None if lift is None else (lift.points, lift.colors)
    if bg is not None and len(bg):
        k = ctx.run.ref
        uv, _ = scene.cameras[k].project(bg)
        iu = np.clip(uv[:, 0].astype(int), 0, scene.cameras[k].width - 1)
        iv = np.clip(uv[:, 1].astype(int), 0, scene.cameras[k].height - 1)
        seed_points = (bg, np.asarray(full[k], np.float32)[iv, iu, :3])  # the reference's inpaint colours
    if lift is not None:
        ctx.note(
            f"insertion: {len(lift.points)} lifted points seed the model; hull depth is the prior on the edit"
        )
    if rcfg.bg_depth:
        ctx.note("background depth: every view's mask is held to the surrounding surfaces' depth (D_bg)")
    res = run_refgs(scene_m, full, ctx.out, rcfg, budget_minutes=None, iters=iters,
                    schedule_iters=int(ctx.settings["schedule_iters"]),
                    max_seconds=cap, replan_seconds=cap / CAP_FACTOR if cap else None,
                    device=cfg.device, seed=cfg.seed,
                    seed_points=seed_points, callback=attach,
                    known_depth=None if lift is None else lift.depth,
                    object_masks=ctx.run.masks if "0_refine" in ctx.inputs else None,
                    exclude=_observed_excluded(ctx, masks))  # fmt: skip
    replan = res.get("replan")
    if replan and replan.get("steps") != iters:  # the note above named the count before Ref-GS's own plan
        first, mean = replan["first_seconds_per_step"], replan["mean_seconds_per_step"]
        ctx.note(f"Ref-GS: {replan['steps']} steps from its own first steps ({first:.3f} s each, "
                 f"{mean:.3f} s on average with growth); {res['steps']} ran")  # fmt: skip
    return res


def _observed_excluded(
    ctx: StageContext[RunInputs], refined: list[np.ndarray]
) -> list[np.ndarray | None] | None:
    """Per scene view, the observed part of the refined split (the input mask less M^rmv_n, as
    0_refine/observed holds it) when the run leaves it out of the photometric loss
    (`CoInConfig.observed` "captures"), else None. `refined`: the stage's masks (`_scene_views`)."""
    cfg = ctx.run.cfg
    if cfg.observed != "captures" or "0_refine" not in ctx.inputs:
        return None
    scene, given = ctx.run.scene, ctx.run.masks
    train = set(scene.train_idx)
    return [np.asarray(given[i], bool) & ~np.asarray(refined[i], bool) if i in train else None
            for i in range(len(scene))]  # fmt: skip


def refgs_settings(cfg: CoInConfig, ref: int, edited: np.ndarray | None) -> RefGSConfig:
    """Ref-GS's settings in this run (what the 2_refgs key records): `CoInConfig.refgs_settings`,
    and in an insertion (an edited reference or a prompt) no background depth, since the masks hold
    the new object, not the background, and the adaptive weights on whole views: the reference, the
    one view that shows the object, says where it ends also outside its mask, where the other views'
    captures show the empty scene (weighed in the mask alone, the object's colour leaked into 3% of
    the far pixels of a view of the synthetic room). An object lifted from one photo
    (`InsertConfig.regions` "derive") is seen in every view's stage-1 image as the same lifted
    geometry, so no view needs the reference to arbitrate: every view weighs the same (weighted 50x,
    the reference alone shaped the object and it rendered as a haze from the side; docs/RUN.md,
    "Insertion on a real capture")."""
    rcfg = cfg.refgs_settings(ref)
    if edited is None and not cfg.prompt:
        return rcfg
    rcfg = replace(rcfg, bg_depth=False, weight_region="view")
    if lifts_one_photo(cfg, edited):
        rcfg = replace(rcfg, adaptive_weights=False)
    return rcfg


def lifts_one_photo(cfg: CoInConfig, edited: np.ndarray | None) -> bool:
    """Whether this run inserts an object lifted from the edited reference alone (regions derived)."""
    return edited is not None and cfg.insert.propagate and cfg.insert.regions == "derive"


def carves(cfg: CoInConfig, edited: np.ndarray | None) -> bool:
    """Whether this run carves (removal with Ref-GS; see `CoInConfig.carve`)."""
    return cfg.carve and _removal_with_refgs(cfg, edited)


def seeds_background(cfg: CoInConfig, edited: np.ndarray | None) -> bool:
    """Whether this run seeds anchors on the background behind the object (removal with Ref-GS;
    see `CoInConfig.seed_background`)."""
    return cfg.seed_background and _removal_with_refgs(cfg, edited)


def _removal_with_refgs(cfg: CoInConfig, edited: np.ndarray | None) -> bool:
    return "refgs" not in cfg.skip and edited is None and not cfg.prompt


def _background_hook(ctx: StageContext[RunInputs], scene: Scene, masks: list[np.ndarray], train: list[int]):
    """(trainer callback that gives the model the carve volume, or None when this run does not
    carve; seed points on the background behind the object in the reference view, or None when this
    run does not seed). Both come from the carve's background depth D_bg (`gs.carve`)."""
    cfg = ctx.run.cfg
    carve, seed = carves(cfg, ctx.run.edited), seeds_background(cfg, ctx.run.edited)
    if not (carve or seed):
        return None, None
    from coin_cl.gs.carve import background_points, build_carve

    cams = [scene.cameras[i] for i in train]
    vol = build_carve(cams, [masks[i] for i in train], np.asarray(scene.points), cfg.carve_cfg)
    if vol is None:
        ctx.note("no background depth behind the object (too few sparse points around the masks): "
                 "no carve, no background seeds")  # fmt: skip
        return None, None
    pts = None
    if seed:
        ref = ctx.run.ref
        with_mask = [i for i in train if np.asarray(masks[i]).any()]
        j = with_mask.index(ref) if ref in with_mask else None  # the carve holds the views with a mask
        pts = np.zeros((0, 3), np.float32) if j is None else background_points(vol, j)
        import torch

        inside = vol.contains(torch.as_tensor(pts)).numpy() if len(pts) else np.zeros(0, bool)
        pts = pts[~inside]  # on the background surface, not in front of it
        ctx.note(f"{len(pts)} points on the background behind the object in the reference view seed "
                 f"anchors (D_bg from {len(scene.points)} sparse points), coloured by its fill")  # fmt: skip
    if not carve:
        return None, pts
    ctx.note(f"carving the object's volume: D_bg from {len(scene.points)} sparse points in {len(vol)} views")

    def attach(trainer, step):
        if getattr(trainer.model, "carve", "n/a") is None:
            trainer.model.carve = vol

    return attach, pts


def stage_clg_adapter(ctx: StageContext[RunInputs]) -> dict:
    from coin_cl.pipeline.clg import stage_clg

    scene, masks, _ = _scene_views(ctx)
    return stage_clg(ctx, scene, masks)


def stage_ted(ctx: StageContext[RunInputs]) -> dict:
    import torch

    from coin_cl.gs.data import views_from_scene
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME, TrainConfig
    from coin_cl.pipeline.ted import run_ted
    from coin_cl.scene.io import read_image

    scene, masks, train = _scene_views(ctx)
    cfg = ctx.run.cfg
    inp = _targets(ctx, ctx.inputs["1_inpaint"])
    guided = dict(inp)
    if "3_clg" in ctx.inputs:
        for i in train:
            p = ctx.inputs["3_clg"] / "images" / (Path(scene.cameras[i].name).stem + ".png")
            if p.is_file():
                guided[i] = read_image(p)
    else:
        ctx.note("w/o CLG: TE-D fine-tunes on the initial inpaints I^_n")
    views = views_from_scene(scene, train, [guided.get(i, scene.images[i]) for i in range(len(scene))])
    excluded = _observed_excluded(ctx, masks)
    for v, i in zip(views, train, strict=True):
        v.meta.update(real=torch.as_tensor(inp[i]), mask=masks[i])
        if excluded is not None and excluded[i] is not None:
            v.exclude = torch.as_tensor(excluded[i])
    model = load_model(ctx.inputs["2_refgs"], CKPT_NAME, model_from_state)
    model.device = cfg.device
    # The schedule the stage's key holds: the same pure function of the plan and the manifests.
    sched = ted_schedule(ctx.run.out, ctx.run.plan, cfg.budget_minutes)
    it = sched.steps
    ctx.note("TE-D: " + ", ".join(
        f"{k} {it[k]} steps" + ("" if k not in sched.caps
                                else f" (~{sched.caps[k] / 60 / CAP_FACTOR:.1f} min)")
        for k in ("ted_finetune", "ted_adversarial")))  # fmt: skip
    rate = sched.refgs_seconds_per_step
    for k in sched.caps:
        ctx.note(f"TE-D {k}: {it[k]} steps planned from what the budget has left"
                 + ("" if rate is None else f" at Ref-GS's measured {rate:.3f} s/step")
                 + f" (the probe's plan: {ctx.run.plan.steps[k]})")  # fmt: skip
    # The plan's counts (explicit ones included, `coin_plan.explicit_steps`) and the run's seed where
    # TEDConfig leaves them to the run (None); the user's config is not changed.
    seed = cfg.seed if cfg.ted.seed is None else cfg.ted.seed
    tcfg = replace(
        cfg.ted, iters_finetune=it["ted_finetune"], iters_adversarial=it["ted_adversarial"], seed=seed
    )
    extra = _ted_bg_depth(ctx, scene, train)
    caps = {phase: sched.caps.get(f"ted_{phase}", 0.0) for phase in ("finetune", "adversarial")}
    res, _ = run_ted(
        model,
        views,
        [],
        ctx.out,
        tcfg,
        TrainConfig(
            model=model.kind, seed=cfg.seed, export_ply=True, aux_grad_ratio=ctx.run.refgs_cfg.aux_grad_ratio
        ),
        extra_terms=extra,
        max_seconds=caps,
        steps_before=refgs_rate(ctx.run.out)[0],
    )
    if not any(ctx.out.rglob(CKPT_NAME)):
        # Both phases had 0 iterations (a tiny budget or explicit settings): the stage passes the
        # Ref-GS scene through unchanged, so that eval and resumption find a checkpoint here.
        from coin_cl.atomic import copy_file

        copy_file(latest_ckpt(ctx.inputs["2_refgs"], CKPT_NAME), ctx.out / CKPT_NAME)
        ctx.note("TE-D ran 0 iterations: the Ref-GS scene is passed through unchanged")
        res["passed_through"] = True
    return jsonable(res)


def _ted_bg_depth(ctx: StageContext[RunInputs], scene: Scene, train: list[int]) -> list[LossTerm]:
    """TE-D keeps Ref-GS's background depth term (the same D_bg, saved by Ref-GS), so fine-tuning
    on the guided images does not grow the ghost back; none when Ref-GS ran without it."""
    from coin_cl.gs.refgs import background_depth_term
    from coin_cl.pipeline.refgs import read_bg_depths

    folder = ctx.inputs["2_refgs"] / "bg_depths"
    rcfg = ctx.run.refgs_cfg
    if not (rcfg.bg_depth and folder.is_dir()):
        return []
    bg = read_bg_depths(folder, scene, train)
    if all(d is None for d in bg):
        return []
    ctx.note(f"TE-D keeps the background depth term on {sum(d is not None for d in bg)} views")
    return [background_depth_term(rcfg, bg, [np.asarray(ctx.run.masks[i], bool) for i in train])]
