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

Budget: the paper's iteration counts (10k Ref-GS, 200 CLG steps, 10k + 10k TE-D) are far beyond
2 CPU cores; `budget_minutes` scales them by a throughput estimate in one place
(`STEPS_PER_MINUTE` at a reference pixel count), so runs are deterministic in their iteration
counts (a time cap would make resumed runs differ) and the log records the time really spent.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from coin_cl.pipeline.inpaint2d import Inpaint2DConfig, effective_config, read_inpaints, run_inpaint2d
from coin_cl.pipeline.insert import InsertConfig
from coin_cl.pipeline.refine_masks import RefineConfig
from coin_cl.pipeline.runner import Stage, StageContext, check_output_folder, run_stages
from coin_cl.pipeline.ted import TEDConfig

log = logging.getLogger(__name__)

# Steps per minute of the GS stages (Ref-GS, TE-D) on the project's 2-core machine kind, measured
# in full CoIn runs (docs/RESULTS.md): 69 Ref-GS / 84 TE-D fine-tune / 68 TE-D adversarial steps per
# minute on SPIn-NeRF at 504x284 (about 950k Scaffold primitives), 226 Ref-GS steps per minute on
# the demo room at 192x144 (5.2x fewer pixels). The rate scales with the pixel ratio to the power
# RATE_EXPONENT, fitted to those two points.
STEPS_PER_MINUTE = 70.0
REF_PIXELS = 504 * 284
RATE_EXPONENT = 0.7
# Shares of the budget: the scene prior's training, Ref-GS, TE-D fine-tune, TE-D adversarial
# (CLG is counted in sampling steps, not minutes).
BUDGET_SHARES = {"prior": 0.15, "refgs": 0.35, "ted_finetune": 0.2, "ted_adversarial": 0.3}
# The scene prior's training time never drops below this under the budget rule: measured on 2
# cores (docs/BENCHMARKS.md, "Diffusion"), 1 minute (27 steps) leaves it untrained (its fills are
# noise) and 2 minutes (133 steps) gives textured fills. An explicit `prior_seconds` is obeyed
# (with a warning below the floor), for smoke tests.
PRIOR_MIN_SECONDS = 120.0
STAGES = ("0_scene", "0_refine", "1_inpaint", "2_refgs", "3_clg", "4_ted", "eval")


@dataclass
class CoInConfig:
    """mask: "seg" | "bbox" | "scribble" (derived from the scene's segmentation masks).
    ref: reference view (index or name); None chooses by `coin_cl.gs.refgs.choose_reference`.
    prompt: text for insertion (needs SD2 weights). budget_minutes: total training time to aim at.
    resolution: image scale (0.5 = half). sd_path / dino_path: local weights (else the embedded
    defaults, named in the log). skip: stage keys to leave out ("refgs", "clg", "ted").
    iters_*, prior_seconds: explicit iteration counts and the scene prior's training seconds (override
    the budget rule; see PRIOR_MIN_SECONDS). seed, device: as everywhere.
    edited_ref: path of the reference view edited by the user (insertion without weights,
    `coin_cl.pipeline.insert`); `inpaint(edited_ref=...)` also takes an array. insert: its settings.
    masks: "input" (inpaint the whole masks) or "refined" (3D-first, supplement C.2: stage 0_refine
    narrows them to the pixels no other view sees, `coin_cl.pipeline.refine_masks`; for removal
    on wide captures). refine: its settings."""

    mask: str = "seg"
    mask_dilate: int = 0
    ref: int | str | None = None
    prompt: str = ""
    budget_minutes: float = 30.0
    resolution: float = 1.0
    sd_path: str | None = None
    dino_path: str | None = None
    skip: tuple[str, ...] = ()
    seed: int = 0
    device: str | None = None
    iters_refgs: int | None = None
    iters_ted_finetune: int | None = None
    iters_ted_adversarial: int | None = None
    prior_seconds: float | None = None
    inpaint2d: Inpaint2DConfig = field(default_factory=Inpaint2DConfig)
    ted: TEDConfig = field(default_factory=TEDConfig)
    refgs: Any = None  # coin_cl.gs.refgs.RefGSConfig (default built on use)
    clg: Any = None  # coin_cl.pipeline.clg.CLGConfig (default built on use)
    edited_ref: str | None = None
    insert: InsertConfig = field(default_factory=InsertConfig)
    masks: str = "input"
    refine: RefineConfig = field(default_factory=RefineConfig)

    def with_iters(self, n: int | None) -> CoInConfig:
        """This config with every GS training stage set to `n` steps (None: unchanged)."""
        if n is None:
            return self
        return replace(self, iters_refgs=n, iters_ted_finetune=n, iters_ted_adversarial=n)

    def iterations(self, width: int, height: int) -> dict[str, int | float]:
        """Iteration counts (and the prior's seconds) from the budget rule, explicit values winning."""
        rate = STEPS_PER_MINUTE * (REF_PIXELS / max(1, width * height)) ** RATE_EXPONENT
        b = {k: v * self.budget_minutes for k, v in BUDGET_SHARES.items()}
        return {
            "prior_seconds": self.prior_seconds
            if self.prior_seconds is not None
            else max(PRIOR_MIN_SECONDS, 60.0 * b["prior"]),
            "refgs": self.iters_refgs if self.iters_refgs is not None else max(1, round(rate * b["refgs"])),
            "ted_finetune": self.iters_ted_finetune
            if self.iters_ted_finetune is not None
            else round(rate * b["ted_finetune"]),
            "ted_adversarial": self.iters_ted_adversarial
            if self.iters_ted_adversarial is not None
            else round(rate * b["ted_adversarial"]),
        }


@dataclass
class CoInResult:
    """out: the run folder; ply: the final Gaussians (standard 3DGS layout); renders: test-view
    images; metrics: the evaluation document (None without ground truth); model: the final model;
    stages: the runner's records."""

    out: Path
    ply: Path | None
    renders: Path | None
    metrics: dict | None
    model: Any
    stages: dict[str, dict]


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "__dataclass_fields__"):
        return _jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    return obj if isinstance(obj, str | int | float | bool | type(None)) else str(obj)


def scene_id(scene) -> dict[str, Any]:
    """What names a scene for the output folder check: its path and a hash of its pixels."""
    h = hashlib.sha256()
    for img in scene.images:
        h.update(np.ascontiguousarray(img[::7, ::7]).tobytes())
    return {
        "path": str(scene.path) if scene.path else None,
        "n_views": len(scene),
        "pixels": h.hexdigest()[:16],
    }


def _train_masks(scene, cfg: CoInConfig) -> list[np.ndarray]:
    from coin_cl.scene.masks import derive_mask

    out = []
    for i, m in enumerate(scene.masks):
        if i in scene.train_idx and m.any():
            out.append(derive_mask(m, cfg.mask, seed=cfg.seed + i, dilate=cfg.mask_dilate))
        else:
            out.append(np.asarray(m, bool))
    return out


def inpaint(
    scene,
    out: str | Path,
    *,
    masks: str | list[np.ndarray] | None = None,
    reference: int | str | None = None,
    prompt: str | None = None,
    budget: float | None = None,
    config: CoInConfig | None = None,
    device: Any = None,
    force: tuple[str, ...] = (),
    edited_ref: str | Path | np.ndarray | None = None,
) -> CoInResult:
    """Remove the masked object in a captured scene, or insert one: from a text prompt (SD2
    weights) or from one view edited by the user (`edited_ref`, no weights needed).

    Args:
        scene: a `coin_cl.scene.Scene` or a folder `load_scene` reads.
        out: the run folder (created; a rerun resumes and skips what is up to date).
        masks: "seg" | "bbox" | "scribble", or per-view (H, W) bool arrays replacing the scene's.
        reference: the reference view (index or name; default: chosen by rule).
        prompt: text for insertion (needs Stable Diffusion 2 weights: `config.sd_path`).
        budget: minutes of training to aim at (default `config.budget_minutes`).
        config: everything else (`CoInConfig`). device: the OpenCL device (Runtime or name).
        edited_ref: the reference view edited in a 2D tool (a path, or (H, W, 3) uint8 / float in
            [0, 1]) at the captured or the run's resolution; the masks must cover where the object
            is to appear in every view. Its view is `reference` or, without one, the training view
            it matches outside the mask (`coin_cl.pipeline.insert`).
    Returns:
        `CoInResult` (paths, metrics, final model).
    """
    from coin_cl.scene import load_scene

    cfg = config or CoInConfig()
    if isinstance(masks, str):
        cfg = replace(cfg, mask=masks)
    if reference is not None:
        cfg = replace(cfg, ref=reference)
    if prompt is not None:
        cfg = replace(cfg, prompt=prompt)
    if budget is not None:
        cfg = replace(cfg, budget_minutes=float(budget))
    if device is not None:
        cfg = replace(cfg, device=device if isinstance(device, str) else getattr(device, "name", None))
    if isinstance(scene, str | Path):
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
    if cfg.masks not in ("input", "refined"):
        raise ValueError(f"masks must be 'input' or 'refined', got {cfg.masks!r}")
    if cfg.masks == "refined" and (cfg.prompt or edited_ref is not None or cfg.edited_ref):
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
    if cfg.resolution != 1.0:
        scene = scene.resized(cfg.resolution)
    if not any(scene.masks[i].any() for i in scene.train_idx):
        raise ValueError(
            f"scene {scene.path} has no training view with a mask: nothing to inpaint "
            "(give masks, e.g. a label/ or masks/ folder)"
        )
    from coin_cl.pipeline.memory import check_memory

    log.info("memory: about %.1f GiB needed at most", check_memory(scene).bytes / 2**30)  # issue 25
    edited = None
    if edited_ref is not None or cfg.edited_ref:
        from coin_cl.pipeline.insert import load_edited

        src = edited_ref if edited_ref is not None else cfg.edited_ref
        cam = scene.cameras[scene.train_idx[0]]
        full = (round(cam.width / cfg.resolution), round(cam.height / cfg.resolution))
        edited = load_edited(src, (cam.width, cam.height), full if cfg.resolution != 1.0 else None)
    out = Path(out)
    check_output_folder(out, scene_id(scene))
    return _run(scene, out, cfg, force, edited)


def _run(
    scene, out: Path, cfg: CoInConfig, force: tuple[str, ...], edited: np.ndarray | None = None
) -> CoInResult:
    from coin_cl.gs.refgs import RefGSConfig, choose_reference

    masks = _train_masks(scene, cfg)
    train = list(scene.train_idx)
    if edited is not None:
        from coin_cl.pipeline.insert import check_edit, find_reference

        ref = find_reference(edited, scene, masks, train, cfg.ref, cfg.insert.ref_match_tol)
        check_edit(
            edited, scene.images[ref], masks[ref], scene.cameras[ref].name, cfg.insert
        )  # before any stage
    else:
        ref = choose_reference(masks, scene.cameras, train_idx=train, ref=cfg.ref)
    cam = scene.cameras[train[0]]
    iters = cfg.iterations(cam.width, cam.height)
    if iters["prior_seconds"] < PRIOR_MIN_SECONDS and not cfg.sd_path:
        log.warning(
            "the scene prior gets %.0f s of training (prior_seconds); below %.0f s it is measured to be "
            "untrained on 2 cores and its fills are noise: use this for smoke tests only",
            iters["prior_seconds"], PRIOR_MIN_SECONDS,
        )  # fmt: skip
    # Ref-GS trains around the pipeline's reference, the one CLG warps from: left to its own rule it
    # would choose again from the masks it is given (refined masks, insertion footprints), or ignore
    # --ref, and P_k would then come from another view than CLG's camera k.
    refgs_cfg = replace(cfg.refgs or RefGSConfig(), ref=ref)
    shared = {"scene": scene, "masks": masks, "ref": ref, "cfg": cfg, "iters": iters, "refgs_cfg": refgs_cfg,
              "edited": edited}  # fmt: skip
    log.info(
        "CoIn: %d training views (%d with a mask), reference view %d (%s), %s masks, iterations %s",
        len(train), sum(masks[i].any() for i in train), ref, scene.cameras[ref].name, cfg.mask, iters,
    )  # fmt: skip
    base = {"seed": cfg.seed, "resolution": cfg.resolution, "mask": cfg.mask, "dilate": cfg.mask_dilate}
    # The edited image's content (not its path) decides whether stage 1 and what follows rerun.
    edit = None if edited is None else {"sha256": hashlib.sha256(edited.tobytes()).hexdigest(),
                                        "ref": ref, "cfg": _jsonable(cfg.insert)}  # fmt: skip
    refined = cfg.masks == "refined"
    r = ["0_refine"] if refined else []  # read by every stage that sees the views' masks
    stages = [
        Stage("0_scene", _stage_scene, settings=base),
        *([Stage("0_refine", _stage_refine, ["0_scene"],
                 {"cfg": _jsonable(cfg.refine), "iters": iters["refgs"]})] if refined else []),
        Stage("1_inpaint", _stage_inpaint, ["0_scene", *r],
              {"cfg": _jsonable(cfg.inpaint2d), "prior_seconds": iters["prior_seconds"],
               "sd": cfg.sd_path, "prompt": cfg.prompt, "edited_ref": edit}),
        Stage("2_refgs", _stage_refgs, ["0_scene", *r, "1_inpaint"],
              {"cfg": _jsonable(refgs_cfg), "ref": ref, "iters": iters["refgs"],
               "plain": "refgs" in cfg.skip}),
        Stage("3_clg", _stage_clg, ["0_scene", *r, "1_inpaint", "2_refgs"],
              {"cfg": _jsonable(cfg.clg), "ref": ref, "dino": cfg.dino_path},
              skip="asked (--skip-stage clg)" if "clg" in cfg.skip else None),
        Stage("4_ted", _stage_ted,
              ["0_scene", *r, "1_inpaint", "2_refgs"] + ([] if "clg" in cfg.skip else ["3_clg"]),
              {"cfg": _jsonable(cfg.ted), "iters": [iters["ted_finetune"], iters["ted_adversarial"]]},
              skip="asked (--skip-stage ted)" if "ted" in cfg.skip else None),
    ]  # fmt: skip
    final = "2_refgs" if "ted" in cfg.skip else "4_ted"
    stages.append(Stage("eval", _stage_eval, ["0_scene", final], {"final": final}))
    records = run_stages(out, stages, shared, force)
    ev = records["eval"].get("result", {})
    from coin_cl.gs.trainer import CKPT_NAME, model_from_state

    model = _load_model(out / final, CKPT_NAME, model_from_state)
    return CoInResult(
        out=out,
        ply=out / "eval" / "point_cloud.ply",
        renders=out / "eval" / "renders",
        metrics=ev.get("metrics"),
        model=model,
        stages=records,
    )


def _latest_ckpt(folder: Path, ckpt_name: str) -> Path:
    cands = sorted(folder.rglob(ckpt_name), key=lambda p: p.stat().st_mtime)
    if not cands:
        raise FileNotFoundError(f"no {ckpt_name} under {folder}")
    return cands[-1]


def _load_model(folder: Path, ckpt_name: str, model_from_state):
    import torch

    state = torch.load(_latest_ckpt(folder, ckpt_name), weights_only=False)
    return model_from_state(state["model"])


# -- stages -----------------------------------------------------------------------------------------


def _stage_scene(ctx: StageContext) -> dict:
    from coin_cl.scene import save_scene

    scene, masks = ctx.shared["scene"], ctx.shared["masks"]
    save_scene(replace(scene, masks=masks), ctx.out / "scene")
    empty = [scene.cameras[i].name for i in scene.train_idx if not masks[i].any()]
    if empty:
        ctx.note(f"{len(empty)} training views have no mask and are kept as captured: {empty[:5]}...")
    area = [float(masks[i].mean()) for i in scene.train_idx]
    return {"views": len(scene), "train": len(scene.train_idx), "test": len(scene.test_idx),
            "mask": ctx.shared["cfg"].mask, "mean_mask_area": float(np.mean(area))}  # fmt: skip


def _scene_views(ctx: StageContext):
    """(scene, masks, training views) as the stage sees them: the input masks; with refined masks
    (stage 0_refine) M^rmv_n and the captures with R^rmv_n in the rest of the input mask; after an
    insertion's stage 1 the object's footprints F_n (`coin_cl.pipeline.insert`), which are the only
    pixels that change (the rest of the input mask is captured background)."""
    scene, masks = ctx.shared["scene"], ctx.shared["masks"]
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


def _stage_refine(ctx: StageContext) -> dict:
    from coin_cl.pipeline.refine_masks import refine_masks

    scene, masks = ctx.shared["scene"], ctx.shared["masks"]
    cfg: CoInConfig = ctx.shared["cfg"]
    res = refine_masks(scene, masks, list(scene.train_idx), ctx.out, cfg.refine, ctx.settings["iters"],
                       cfg.seed, cfg.device)  # fmt: skip
    ctx.note(f"refined masks: {res['refined_px']} of {res['input_px']} mask px left to inpaint "
             f"({res['refined_ratio']:.0%}); per view in 0_refine/areas.json")  # fmt: skip
    return res


def _sd2(cfg: CoInConfig):
    if not cfg.sd_path:
        return None
    from coin_cl.diffusion.sd2 import SD2Denoiser

    return SD2Denoiser.from_pretrained(cfg.sd_path)


def _stage_inpaint(ctx: StageContext) -> dict:
    scene, masks, train = _scene_views(ctx)
    cfg: CoInConfig = ctx.shared["cfg"]
    if ctx.shared.get("edited") is not None:
        from coin_cl.pipeline.insert import run_insert

        res = run_insert(scene, masks, train, ctx.shared["ref"], ctx.shared["edited"], ctx.out, cfg.insert,
                         cfg.device)  # fmt: skip
        ctx.note(f"initial images: {res['source']}; {res['views_without_object']} views without the object")
        return res
    cam = scene.cameras[train[0]]
    icfg = effective_config(
        cfg.inpaint2d, ctx.shared["iters"]["prior_seconds"], cfg.seed, cam.width, cam.height
    )
    res = run_inpaint2d(scene, masks, train, ctx.out, icfg, cfg.mask, sd2=_sd2(cfg), prompt=cfg.prompt)
    for s in res["sources"]:
        ctx.note(f"initial inpainting source: {s}")
    return res


def _targets(ctx: StageContext, folder: Path) -> dict[int, np.ndarray]:
    scene, masks, train = _scene_views(ctx)
    from coin_cl.gs.refgs import composite_targets

    inp = read_inpaints(scene, folder, train)
    # Outside the mask the captured image is the truth (paper 5.1).
    return {i: composite_targets(inp[i], scene.images[i], masks[i]) for i in train}


def _stage_refgs(ctx: StageContext) -> dict:
    from coin_cl.pipeline.refgs import run_refgs

    scene, masks, train = _scene_views(ctx)
    cfg: CoInConfig = ctx.shared["cfg"]
    targets = _targets(ctx, ctx.inputs["1_inpaint"])
    rcfg = ctx.shared["refgs_cfg"]
    if "refgs" in cfg.skip:
        from coin_cl.gs.refgs import RefGSConfig

        rcfg = RefGSConfig(
            adaptive_weights=False,
            feature_attention=False,
            depth_loss=False,
            prune_points=False,
            ref=ctx.shared["ref"],
        )
        ctx.note("w/o Ref-GS: plain Scaffold-GS on the initial inpaints (ablation)")
    scene_m = replace(scene, masks=masks, ref_view=ctx.shared["ref"])
    full = [targets.get(i, scene.images[i]) for i in range(len(scene))]
    from coin_cl.pipeline.insert import read_lift

    lift = read_lift(ctx.inputs["1_inpaint"])
    if lift is not None:
        ctx.note(
            f"insertion: {len(lift.points)} lifted points seed the model; hull depth is the prior on the edit"
        )
    return run_refgs(scene_m, full, ctx.out, rcfg, budget_minutes=None, iters=ctx.shared["iters"]["refgs"],
                     device=cfg.device, seed=cfg.seed,
                     seed_points=None if lift is None else (lift.points, lift.colors),
                     known_depth=None if lift is None else lift.depth)  # fmt: skip


def _stage_clg(ctx: StageContext) -> dict:
    from coin_cl.pipeline.clg import stage_clg

    scene, masks, _ = _scene_views(ctx)
    return stage_clg(ctx, scene, masks)


def _stage_ted(ctx: StageContext) -> dict:
    import torch

    from coin_cl.gs.data import views_from_scene
    from coin_cl.gs.trainer import CKPT_NAME, TrainConfig, model_from_state
    from coin_cl.pipeline.ted import run_ted
    from coin_cl.scene.io import read_image

    scene, masks, train = _scene_views(ctx)
    cfg: CoInConfig = ctx.shared["cfg"]
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
    for v, i in zip(views, train, strict=True):
        v.meta.update(real=torch.as_tensor(inp[i]), mask=masks[i])
    model = _load_model(ctx.inputs["2_refgs"], CKPT_NAME, model_from_state)
    model.device = cfg.device
    it = ctx.shared["iters"]
    tcfg = replace(
        cfg.ted, iters_finetune=it["ted_finetune"], iters_adversarial=it["ted_adversarial"], seed=cfg.seed
    )
    res, _ = run_ted(
        model, views, [], ctx.out, tcfg, TrainConfig(model=model.kind, seed=cfg.seed, export_ply=True)
    )
    if not any(ctx.out.rglob(CKPT_NAME)):
        # Both phases had 0 iterations (a tiny budget or explicit settings): the stage passes the
        # Ref-GS scene through unchanged, so that eval and resumption find a checkpoint here.
        import shutil

        shutil.copy2(_latest_ckpt(ctx.inputs["2_refgs"], CKPT_NAME), ctx.out / CKPT_NAME)
        ctx.note("TE-D ran 0 iterations: the Ref-GS scene is passed through unchanged")
        res["passed_through"] = True
    return _jsonable(res)


def _stage_eval(ctx: StageContext) -> dict:
    import torch

    from coin_cl.gs.trainer import CKPT_NAME, model_from_state
    from coin_cl.scene.io import to_uint8, write_png

    scene = ctx.shared["scene"]
    cfg: CoInConfig = ctx.shared["cfg"]
    final = ctx.settings["final"]
    folder = [p for n, p in ctx.inputs.items() if n == final][0]
    model = _load_model(folder, CKPT_NAME, model_from_state)
    model.device = cfg.device
    rdir = ctx.out / "renders"
    rdir.mkdir(parents=True, exist_ok=True)

    for i in list(scene.test_idx) + list(scene.train_idx):
        with torch.no_grad():
            r = model.render(scene.cameras[i], 10**9)
        write_png(rdir / (Path(scene.cameras[i].name).stem + ".png"), to_uint8(r.image.clamp(0, 1).numpy()))
    from coin_cl.gs.trainer import write_model_ply

    orbit_gif(model, [scene.cameras[i] for i in scene.train_idx], ctx.out / "orbit.gif")
    ply = ctx.out / "point_cloud.ply"
    centers = torch.stack([scene.cameras[i].center_t for i in scene.train_idx])
    write_model_ply(model, ply, centers.mean(0))
    result: dict[str, Any] = {"final_stage": final, "ply": str(ply)}
    gt_ok = scene.test_idx and all(scene.masks[i].any() for i in scene.test_idx)
    if gt_ok:
        from coin_cl.evaluation import evaluate_folder

        doc = evaluate_folder(rdir, ctx.inputs["0_scene"] / "scene", ctx.out / "metrics")
        result["metrics"] = doc["mean"]
    else:
        ctx.note("no ground-truth test views with masks: metrics skipped")
    return _jsonable(result)


def share_stages(
    src: str | Path, dst: str | Path, stages: tuple[str, ...] = ("0_scene", "1_inpaint")
) -> None:
    """Start run folder `dst` from the `stages` folders of run `src` (and its scene record), so a
    comparison row (a baseline, an ablation) reuses them instead of redoing them. Safe by
    construction: the runner reruns any copied stage whose manifest does not match `dst`'s settings.
    Existing folders in `dst` are left alone."""
    import shutil

    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    if (src / "run.json").is_file() and not (dst / "run.json").exists():
        shutil.copy2(src / "run.json", dst / "run.json")
    for name in stages:
        if (src / name / "manifest.json").is_file() and not (dst / name).exists():
            shutil.copytree(src / name, dst / name)


def orbit_gif(model, cameras: list, path: Path, frames: int = 36) -> None:
    """Render `model` along the path through `cameras` (in the given order; slerped rotations,
    interpolated centres: `coin_cl.scene.conventions.interpolate_pose`) into a looping GIF."""
    import imageio.v3 as iio
    import torch

    from coin_cl.scene.conventions import interpolate_pose
    from coin_cl.scene.io import atomic_write, to_uint8

    if not cameras:
        return
    images = []
    for j in range(frames):
        u = j * max(1, len(cameras) - 1) / frames
        a, b = cameras[min(int(u), len(cameras) - 1)], cameras[min(int(u) + 1, len(cameras) - 1)]
        vm = interpolate_pose(a.viewmat, b.viewmat, u - int(u))
        with torch.no_grad():
            r = model.render(replace(a, viewmat=vm, name=f"orbit_{j:03d}"), 10**9)
        images.append(to_uint8(r.image.clamp(0, 1).numpy()))
    atomic_write(path, lambda p: iio.imwrite(p, images, extension=".gif", duration=80, loop=0))


def summary(out: Path) -> dict:
    """The run log (`out/log.json`) as a dict."""
    return json.loads((Path(out) / "log.json").read_text())
