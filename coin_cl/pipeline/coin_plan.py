"""The plan of a CoIn run: `budget`'s rules applied to a `CoInConfig` (its step counts, budget,
probes and the rates another run measured). `budget` knows nothing of `CoInConfig`, so the modules
the config is made of (`refine_masks`, through `pipeline.refgs`) can use its rules without an
import cycle."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from coin_cl.pipeline.budget import (
    BUDGET_SHARES,
    PLAN_FILE,
    PRIOR_MIN_SECONDS,
    REFINE_SHARE,
    Plan,
    plan_run,
    probe_seconds_per_step,
    read_plan,
)
from coin_cl.pipeline.config import CoInConfig

if TYPE_CHECKING:
    import numpy as np

    from coin_cl.scene import Scene

log = logging.getLogger(__name__)

# A timing probe: () -> seconds (per step, or added to a step); None where the run needs none.
Probe = Callable[[], float] | None


def plan_for(
    scene: Scene, out: Path, cfg: CoInConfig, train: list[int], edited: np.ndarray | None = None
) -> Plan:
    """The plan of a CoIn run (`train` its training views; `edited`: an insertion's edited reference):
    `plan_run` keyed by the settings the step counts depend on, probing `scene` at its working size."""
    cam = scene.cameras[train[0]]
    explicit = explicit_steps(cfg)
    skip_adv = adversarial_skip(scene, cfg) if explicit["ted_adversarial"] is None else None
    shares, skipped = dict(BUDGET_SHARES), {}
    if skip_adv:
        log.info("TE-D's adversarial phase skipped: %s (an explicit count runs it: --iters, "
                 "CoInConfig.iters_ted_adversarial)", skip_adv)  # fmt: skip
        explicit["ted_adversarial"] = 0
        skipped = {"ted_adversarial": f"skipped: {skip_adv}"}
        # its minutes go to the fine-tune phase, which trains on CLG's images (measured on a real
        # capture: 2.5x the fine-tune steps, masked VGG distance -18%, PSNR +1.2 dB; docs/RESULTS.md)
        both = BUDGET_SHARES["ted_finetune"] + BUDGET_SHARES["ted_adversarial"]
        shares = {**shares, "ted_adversarial": 0.0, "ted_finetune": both}
    if "ted" in cfg.skip:  # no TE-D: 0 steps given, the GS pool is Ref-GS's (and the split's)
        shares = {**shares, "ted_finetune": 0.0, "ted_adversarial": 0.0}
        explicit["ted_finetune"] = explicit["ted_adversarial"] = 0
    if cfg.inpaint_region == "refined" and cfg.refine.iters is None:
        shares["refine"] = REFINE_SHARE  # 0_refine's fit; a given count (RefineConfig.iters) is not planned
    key = {"budget_minutes": cfg.budget_minutes, "resolution": cfg.resolution, "device": cfg.device,
           "size": [cam.width, cam.height], "train_views": len(train), "seed": cfg.seed,
           "explicit": [*explicit.values(), cfg.prior_seconds], **skipped,
           # the budget holds every stage (stage_costs): which stages the run has decide its split
           "clock": {"region": cfg.inpaint_region, "skip": sorted(cfg.skip)}}  # fmt: skip
    if clg_skip_reason(cfg, edited) and "clg" not in cfg.skip:  # an insertion, or no sampler to run
        key["clock"]["clg"] = "left out"
    probes = (lambda: probe_seconds_per_step(scene, train, cfg.device, cfg.seed),
              prior_probe(cfg, cam.width, cam.height), disc_probe(cfg, cam.width, cam.height))  # fmt: skip
    wall = None
    if cfg.rates_from is not None:
        key["rates_from"] = str(cfg.rates_from)  # only when set: plans made before keep their key
        probes = inherited_rates(Path(cfg.rates_from), *probes)
        wall = read_plan(Path(cfg.rates_from) / PLAN_FILE).probe_wall_seconds
    if shares == BUDGET_SHARES:
        shares = None  # the default split: plans made before keep their file
    return plan_run(out, key, cfg.budget_minutes, explicit, cfg.prior_seconds, *probes, shares=shares,
                    views=fixed_views(scene, cfg, train, edited), probe_wall_seconds=wall,
                    prior_trained=prior_trained(scene, cfg), view_pixels=cam.width * cam.height)  # fmt: skip


def clg_skip_reason(cfg: CoInConfig, edited: np.ndarray | None) -> str | None:
    """Why this run leaves CLG out (None: it runs): asked; an insertion (an edited reference, or
    a prompt SD2 draws into the reference) whose stage 1 lifts the object (`InsertConfig.propagate`),
    where every view's initial image is already the reference warped through the lifted object; or a
    removal with no sampler to run (no SD2, `CLGConfig.prior_sampler` off) where
    `CLGConfig.without_sampler` does not ask for the propagation alone."""
    if "clg" in cfg.skip:
        return "asked (--skip-stage clg)"
    if (edited is not None or cfg.prompt) and cfg.insert.propagate:
        return (
            "an insertion: stage 1's images are the reference (edited, or drawn by SD2) warped through the "
            "lifted object, one answer in every view already (CLG's warp through Ref-GS's depth, P_k, "
            "gave a sparser copy of it, speckled with the surface behind)"
        )
    removal = edited is None and not cfg.prompt  # an insertion's CLG carries its object (propagate False)
    if removal and not cfg.sd_path and not clg_samples(cfg) and not cfg.clg_settings().without_sampler:
        return (
            "no sampler to run (no Stable Diffusion 2, CLGConfig.prior_sampler off), and CLG's propagation "
            "alone scored below leaving it out on real scenes (docs/BENCHMARKS.md); TE-D fits stage 1's "
            "images (--clg propagate or CLGConfig.without_sampler runs it)"
        )
    return None


def fixed_views(
    scene: Scene, cfg: CoInConfig, train: list[int], edited: np.ndarray | None = None
) -> dict[str, int]:
    """{fixed stage: the views it works on} for `stage_costs.fixed_costs`: 0_scene and eval every
    view, CLG the masked training views (absent when left out, `clg_skip_reason`; "3_clg_propagate"
    when it runs without a sampler), stage 1 the masked training views it
    fills by computation (with the dataset's own fills only those without one: the rest are read);
    "eval_capture": the masked test views eval also scores at the capture's size (a run below it)."""
    from coin_cl.pipeline.inpaint2d import fill_source

    masked = [i for i in train if scene.masks[i].any()]
    filled = masked
    if fill_source(scene, cfg.inpaint2d, cfg.mask_kind, cfg.sd_path) == "dataset":
        filled = [i for i in masked if i not in scene.priors.get("rgb", {})]
    views = {"0_scene": len(scene), "1_inpaint": len(filled), "3_clg": len(masked), "eval": len(scene)}
    if cfg.resolution not in (None, 1.0):  # eval scores the test views at the capture's size too
        views["eval_capture"] = sum(bool(scene.masks[i].any()) for i in scene.test_idx)
    if clg_skip_reason(cfg, edited):
        del views["3_clg"]
    elif not clg_samples(cfg):  # CLG without a sampler: a warp and a blend per view
        views["3_clg_propagate"] = views.pop("3_clg")
    return views


def clg_samples(cfg: CoInConfig) -> bool:
    """Whether CLG runs a diffusion sampler: with Stable Diffusion 2, or with the embedded scene
    prior where `CLGConfig.prior_sampler` asks; else it is left out (`clg_skip_reason`) or, where
    `CLGConfig.without_sampler` asks, propagates the reference without one (`clg.stage_clg`),
    whatever stage 1's fills are, and the prior's training minutes go to the GS stages. Measured
    (docs/RESULTS.md, docs/BENCHMARKS.md): on the exemplar's fills the guard kept the input in 41 of
    55 views and the run scored higher without the sampler; on SPIn-NeRF's LaMa
    fills at budget 10 the sampler and its prior took 3.9 of the 10 minutes, and without them Ref-GS
    and TE-D trained 909 steps instead of 467 to a level result (m-PSNR +0.03 dB, masked VGG
    distance 2.4% lower, bbox GMSD 1% higher)."""
    clg = cfg.clg_settings()
    if not clg.sample:
        return False
    return bool(cfg.sd_path or clg.prior_sampler)


def prior_trained(scene: Scene, cfg: CoInConfig) -> bool:
    """Whether a stage trains the scene prior: CLG samples with it unless skipped or propagating
    (`clg_samples`), and stage 1 fills with it when its inpainter is the prior. A run with neither
    plans no time for it (logged)."""
    from coin_cl.pipeline.inpaint2d import fill_source

    if "clg" not in cfg.skip and clg_samples(cfg):
        return True
    if fill_source(scene, cfg.inpaint2d, cfg.mask_kind, cfg.sd_path) == "prior" and cfg.inpaint2d.use_prior:
        return True
    why = "CLG is skipped" if "clg" in cfg.skip else "CLG runs no sampler"
    log.info("scene prior: not trained here (%s and stage 1 fills without it): no time planned for it", why)
    return False


def adversarial_skip(scene: Scene, cfg: CoInConfig) -> str | None:
    """Why a run leaves TE-D's adversarial phase out (None: it runs). Its discriminator takes the
    stage-1 fills as the "real" texture (paper 4.4); that transfers a learned inpainter's texture
    (SD2, LaMa), but the embedded fills' texture is a collage of the scene's other patches (exemplar),
    a blur (Telea) or noise (scene prior), and the phase makes exactly that crisp: measured on two
    virtual-object scenes of a real capture, it left the masked VGG distance 24% and 90% worse than
    the fine-tune phase before it (docs/RESULTS.md)."""
    from coin_cl.pipeline.inpaint2d import GENERATIVE_SOURCES, fill_source

    source = fill_source(scene, cfg.inpaint2d, cfg.mask_kind, cfg.sd_path)
    if source in GENERATIVE_SOURCES:
        return None
    return (f"stage 1's fills come from the {source} inpainter, whose texture the discriminator would "
            "make crisp rather than true")  # fmt: skip


def inherited_rates(run: Path, probe: Probe, prior: Probe, disc: Probe) -> tuple[Probe, Probe, Probe]:
    """The three probes of a run that takes its measured rates from the plan of run folder `run`
    (`CoInConfig.rates_from`): each returns that plan's figure instead of measuring again, so a
    comparison row at the same budget gets the same counts (the scene prior's steps, which stage 1's
    key holds, included: probed anew they could differ by a step and redo the shared stages). A
    rate the plan lacks (not probed there) is measured here; a probe this run does not need
    (None) stays None."""
    path = Path(run) / PLAN_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: cannot take the rates from it; run that folder "
                                "first or leave rates_from unset")  # fmt: skip
    have = read_plan(path)

    def take(name: str, own: Probe) -> Probe:
        value = getattr(have, name)
        if own is None or value is None:
            return own
        return lambda: float(value)

    log.info("plan: the measured rates come from %s", path)
    return (take("probe_seconds_per_step", probe), take("prior_seconds_per_step", prior),
            take("disc_seconds_per_step", disc))  # fmt: skip


def disc_probe(cfg: CoInConfig, width: int, height: int) -> Probe:
    """TE-D's discriminator probe for a CoIn run: a callable -> seconds it
    adds to an adversarial step at this image size; None where TE-D is skipped."""
    if "ted" in cfg.skip:
        return None
    from coin_cl.pipeline.ted import TEDConfig, probe_discriminator_seconds

    ted = cfg.ted or TEDConfig()
    return lambda: probe_discriminator_seconds(ted, height, width)


def prior_probe(cfg: CoInConfig, width: int, height: int) -> Probe:
    """The scene prior's timing probe for a CoIn run (views `width` x `height`):
    a callable -> seconds per step of the prior stage 1 and CLG will train; None where no prior is
    trained (SD2 given) or its step count is fixed (`ScenePriorConfig.train_steps`)."""
    if cfg.sd_path or cfg.inpaint2d.prior.train_steps is not None:
        return None
    from coin_cl.diffusion.scene_prior import probe_seconds_per_step as prior_rate
    from coin_cl.pipeline.inpaint2d import effective_config

    prior_cfg = effective_config(cfg.inpaint2d, PRIOR_MIN_SECONDS, cfg.seed, width, height).prior
    return lambda: prior_rate(prior_cfg)


def explicit_steps(cfg: CoInConfig) -> dict[str, int | None]:
    """{"refgs", "ted_finetune", "ted_adversarial": the step count `cfg` gives, or
    None for the plan's}. TE-D's may come from `CoInConfig.iters_ted_*` or `cfg.ted.iters_*`; set in
    both, they must agree (ValueError naming both)."""
    out = {"refgs": cfg.iters_refgs}
    for phase in ("finetune", "adversarial"):
        top, nested = getattr(cfg, f"iters_ted_{phase}"), getattr(cfg.ted, f"iters_{phase}")
        if top is not None and nested is not None and top != nested:
            raise ValueError(f"CoInConfig.iters_ted_{phase}={top} and CoInConfig.ted.iters_{phase}={nested} "
                             "disagree: set one of them")  # fmt: skip
        out[f"ted_{phase}"] = top if top is not None else nested
    return out
