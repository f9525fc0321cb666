"""The run's settings: `CoInConfig`, everything `coin_cl.pipeline.coin.inpaint` takes beyond the scene,
with the settings of each stage it holds (`Inpaint2DConfig`, `RefGSConfig`, `CLGConfig`, `TEDConfig`,
...). Its own module so that the stage functions (`stages`, `eval_stage`) read the type without
importing the module that builds the stage graph; `coin_cl.pipeline.coin` re-exports it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from coin_cl.diffusion.scene_prior import ScenePriorConfig
from coin_cl.gs.carve import CarveConfig
from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
from coin_cl.pipeline.insert import InsertConfig
from coin_cl.pipeline.refine_masks import RefineConfig
from coin_cl.pipeline.ted import TEDConfig
from coin_cl.schema import MAX_STEPS

# The stage folders of a run, in order (`coin_cl.pipeline.coin` builds them).
STAGES = ("0_scene", "0_refine", "1_inpaint", "2_refgs", "3_clg", "4_ted", "eval")


MASK_KINDS = ("seg", "bbox", "scribble")  # CoInConfig.mask_kind
REGIONS = ("auto", "input", "refined")  # CoInConfig.inpaint_region
OBSERVED = ("captures", "target")  # CoInConfig.observed
SKIPPABLE = ("refgs", "clg", "ted")  # CoInConfig.skip: the stages an ablation may leave out


def _choice(field_name: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"CoInConfig.{field_name} is {value!r}: give one of {', '.join(allowed)}")


@dataclass
class CoInConfig:
    """Everything a CoIn run takes beyond the scene (`coin_cl.inpaint`); each field says what it means
    where it is declared. Values are checked here: a bad one is an error naming the field.

    The measurements behind the defaults of `carve` and `observed`: carve at 400 Ref-GS steps cost
    SPIn-NeRF 0.7 dB m-PSNR (13.16 against 13.87), texture (HF ratio 0.41 against 0.49) and GMSD,
    and on the synthetic room gained 1.1 dB m-PSNR but blurred (docs/RESULTS.md). observed
    "captures" against "target" at 1501 GS steps with the rooms' exact masks (one machine): room
    m-PSNR 22.44 / 22.25, HF ratio 0.793 / 0.780, GMSD 0.140 / 0.139; room360 22.49 / 22.44, 0.906 /
    0.862, 0.137 / 0.142 (docs/RESULTS.md, "The observed part from the captures by default").
    `seed_background` on a Zen 3 (docs/BENCHMARKS.md, "Anchors seeded behind the object"): SPIn-NeRF
    at fixed steps m-PSNR 13.27 against 13.04 and masked VGG-PD 3.95 against 4.15, but the cup
    capture's default run at budget 10 lost 0.67 dB m-PSNR (25.15 against 25.82), the reference's
    darker fill spread into every view."""

    # The shape of mask given for the object: "seg" | "bbox" | "scribble" (the latter two derived
    # from the scene's segmentation masks). Default "seg": the paper's main setting.
    mask_kind: str = "seg"
    # Iterations (2 px each) of a 5x5 dilation of the training masks; 0 = as given. None (default):
    # a ring of `scene.masks.MASK_RING_SHARE` (1.4 %) of the longer side at the working size, as
    # SPIn-NeRF's masks (the object's fringe and contact shadow would otherwise be trained as
    # background), but none for a scene whose scene_info.json declares its masks exact (there the
    # ring cost 1 dB, docs/RESULTS.md "Where the rooms' m-PSNR is decided"); resolved value logged.
    mask_dilate: int | None = None
    # The reference view (index or name). None (default): `pipeline.reference.choose_reference`'s
    # rule (largest, most central mask), logged; Ref-GS and CLG both use the one chosen.
    ref: int | str | None = None
    # Text for insertion (needs SD2 weights, `sd_path`). "" (default): removal.
    prompt: str = ""
    # The run's wall-clock minutes (> 0), every stage included; the budget plan subtracts the fixed
    # stages' cost and turns the rest into step counts (`pipeline.budget`), recorded in OUT/plan.json.
    # 10 (default): the knee of the measured curve on SPIn-NeRF scene 1, where twice the minutes scored
    # lower (TE-D's longer run draws needles); on the cup capture 20 scored higher (docs/BENCHMARKS.md,
    # "The curve at today's code").
    budget_minutes: float = 10.0
    # Image scale (0.5 = half size, > 0). None (default): `budget.working_resolution` picks it from
    # the image size (logged).
    resolution: float | None = None
    # Folder of Stable Diffusion 2 inpainting weights (diffusers layout). None (default):
    # $COIN_SD2_PATH, else the embedded scene prior (named in the log).
    sd_path: str | None = None
    # DINO weights for CLG's features. None (default): the analytic features (named in the log).
    dino_path: str | None = None
    # Stage keys to leave out, from SKIPPABLE ("refgs": plain Scaffold-GS instead of Ref-GS, "clg",
    # "ted"): the paper's Table 4 ablations. Default (): the whole method.
    skip: tuple[str, ...] = ()
    # The run's seed (every stage's RNG; a stage config whose seed is None takes it). Default 0.
    seed: int = 0
    # OpenCL device name. None (default): `engine.resolve_device`'s choice.
    device: str | None = None
    # Ref-GS steps (1..MAX_STEPS). None (default): the budget plan's figure (plan.json).
    iters_refgs: int | None = None
    # TE-D fine-tuning steps (0..MAX_STEPS; also `ted.iters_finetune`, which must agree). None
    # (default): the budget plan's figure.
    iters_ted_finetune: int | None = None
    # TE-D adversarial steps (0..MAX_STEPS; also `ted.iters_adversarial`, which must agree). None
    # (default): the budget plan's figure.
    iters_ted_adversarial: int | None = None
    # Steps Ref-GS lays its learning-rate decay and anchor growth out over, its own included
    # (>= its steps, <= MAX_STEPS; a span below the count the plan gives Ref-GS counts as that
    # count). None (default): the plan's rule (`schedule.refgs_schedule_span`:
    # its steps plus the plan's TE-D fine-tune steps where TE-D continues the decay). A row that
    # repeats a default run at its counts gives the span that run used (its 2_refgs/gs/log.json),
    # since Ref-GS and TE-D plan their counts again from measured rates after the span is laid out.
    refgs_schedule_iters: int | None = None
    # Seconds of scene-prior training (>= 0; the prior's own `train_seconds` is this). None
    # (default): the budget's share (`budget.prior_seconds`), recorded in plan.json.
    prior_seconds: float | None = None
    # Stage 1's settings (`pipeline.inpaint2d`).
    inpaint2d: Inpaint2DConfig = field(default_factory=Inpaint2DConfig)
    # TE-D's settings (`pipeline.ted`); its None fields are the run's (plan, seed).
    ted: TEDConfig = field(default_factory=TEDConfig)
    # Ref-GS's settings (`gs.refgs`). None (default): RefGSConfig(). Its `ref` is the run's reference
    # (set `ref` here instead) and its seed None is `seed`.
    refgs: RefGSConfig | None = None
    # CLG's settings (`pipeline.clg_config`). None (default): CLGConfig(); its seed / prompt None
    # are the run's `seed` / `prompt`.
    clg: CLGConfig | None = None
    # Path of the reference view edited by the user (insertion without weights,
    # `pipeline.insert`; `inpaint(edited_ref=...)` also takes an array). None (default): none.
    edited_ref: str | None = None
    # The insertion's settings (`pipeline.insert`).
    insert: InsertConfig = field(default_factory=InsertConfig)
    # What stage 1 inpaints, from REGIONS: "input" (the whole masks), "refined" (3D-first,
    # supplement C.2: stage 0_refine narrows them to the pixels no other view sees; removal only) or
    # "auto" (default; removal: "refined" when `gs.carve.observed_share` estimates that other views
    # see at least `coin.AUTO_REFINE_SHARE` of the masks, else "input"; logged with its figure).
    inpaint_region: str = "auto"
    # The refined masks' settings (`pipeline.refine_masks`).
    refine: RefineConfig = field(default_factory=RefineConfig)
    # Removal carves the object's volume out of the GS for good (`gs.carve`); not with insertion or
    # the w/o Ref-GS row. Default False: with `seed_background` it cost SPIn-NeRF 0.7 dB m-PSNR
    # (class docstring).
    carve: bool = False
    # Removal seeds Ref-GS's anchors on the background surface behind the object in the reference
    # view (D_bg inside its mask, `gs.carve.background_points`), coloured by the reference's fill, so
    # that the hole has primitives from the first step instead of waiting for growth to reach it;
    # not with insertion or the w/o Ref-GS row (so not in the naive row). Default False: one wrong
    # fill in the reference then colours every view (class docstring).
    seed_background: bool = False
    # The carve's settings (`gs.carve`; also the "auto" region's visibility estimate).
    carve_cfg: CarveConfig = field(default_factory=CarveConfig)
    # How the observed part of a refined mask reaches the model, from OBSERVED: "captures"
    # (default: left out of view n's photometric loss, the other views' captures teach it; measured
    # better, class docstring) or "target" (the object-free fit's render is view n's target there).
    # Only refined-mask runs read it.
    observed: str = "captures"
    # A run folder whose plan's measured rates this run's plan takes instead of probing again
    # (`coin_plan.inherited_rates`; the comparison rows of `demo.baseline_config`). None (default): probe.
    rates_from: str | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.budget_minutes, int | float) and math.isfinite(self.budget_minutes)
                and self.budget_minutes > 0):  # fmt: skip
            raise ValueError(
                f"--budget / budget_minutes is {self.budget_minutes!r}: give a positive number "
                "of minutes (the step counts of --iters do not need it, but it must be valid)"
            )
        if self.prior_seconds is not None and not (
            math.isfinite(self.prior_seconds) and self.prior_seconds >= 0
        ):
            raise ValueError(f"--prior-seconds / prior_seconds is {self.prior_seconds!r}: give a number of "
                             "seconds >= 0, or leave it out for the budget's share")  # fmt: skip
        if self.resolution is not None and not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"--resolution / resolution is {self.resolution!r}: give a positive scale, "
                             "e.g. 0.5 for half size")  # fmt: skip
        for name in ("iters_refgs", "iters_ted_finetune", "iters_ted_adversarial"):
            n, low = getattr(self, name), 1 if name == "iters_refgs" else 0
            if n is not None and not (isinstance(n, int | np.integer) and low <= n <= MAX_STEPS):
                raise ValueError(f"--iters / {name} is {n!r}: give a step count in {low}..{MAX_STEPS}")
        span = self.refgs_schedule_iters
        if span is not None and not (isinstance(span, int | np.integer) and not isinstance(span, bool)
                                     and (self.iters_refgs or 1) <= span <= MAX_STEPS):  # fmt: skip
            raise ValueError(f"CoInConfig.refgs_schedule_iters is {span!r}: give a step count from "
                             f"Ref-GS's steps ({self.iters_refgs or 1}) to {MAX_STEPS}, or None (the "
                             "plan's rule)")  # fmt: skip
        _choice("mask_kind", self.mask_kind, MASK_KINDS)
        _choice("inpaint_region", self.inpaint_region, REGIONS)
        _choice("observed", self.observed, OBSERVED)
        if isinstance(self.skip, str):
            raise ValueError(f"CoInConfig.skip is {self.skip!r}: give a tuple of stage keys, "
                             f"e.g. ({self.skip!r},)")  # fmt: skip
        for s in self.skip:
            _choice("skip", s, SKIPPABLE)
        if self.mask_dilate is not None and not (isinstance(self.mask_dilate, int | np.integer)
                                                 and self.mask_dilate >= 0):  # fmt: skip
            raise ValueError(f"CoInConfig.mask_dilate is {self.mask_dilate!r}: give an integer >= 0, "
                             "or None (auto)")  # fmt: skip
        if not (isinstance(self.seed, int | np.integer) and not isinstance(self.seed, bool)):
            raise ValueError(f"CoInConfig.seed is {self.seed!r}: give an integer")
        default = ScenePriorConfig()
        for name, what in (("train_seconds", "CoInConfig.prior_seconds / --prior-seconds"),
                           ("seed", "CoInConfig.seed / --seed (inpaint2d.seed offsets it)")):  # fmt: skip
            given = getattr(self.inpaint2d.prior, name)
            if given != getattr(default, name):
                raise ValueError(f"CoInConfig.inpaint2d.prior.{name} is {given!r}: the run sets it; give "
                                 f"{what} instead")  # fmt: skip
        if self.refgs is not None and self.refgs.ref is not None and self.refgs.ref != self.ref:
            raise ValueError(
                f"CoInConfig.refgs.ref is {self.refgs.ref!r}: Ref-GS trains around the run's reference "
                "(the one CLG warps from); set CoInConfig.ref / --ref instead and leave refgs.ref None"
            )

    def refgs_settings(self, ref: int) -> RefGSConfig:
        """Ref-GS's settings in this run: `refgs` (default RefGSConfig()) with the run's reference
        `ref` and, where its seed is None, the run's seed (what the 2_refgs stage key records)."""
        rcfg = self.refgs or RefGSConfig()
        return replace(rcfg, ref=ref, seed=self.seed if rcfg.seed is None else rcfg.seed)

    def clg_settings(self) -> CLGConfig:
        """CLG's settings in this run: `clg` (default CLGConfig()) with the run's seed and prompt
        where it leaves them None (what the 3_clg stage key records)."""
        c = self.clg or CLGConfig()
        return replace(c, seed=self.seed if c.seed is None else c.seed,
                       prompt=self.prompt if c.prompt is None else c.prompt)  # fmt: skip

    def with_iters(self, n: int | None) -> CoInConfig:
        """This config with every GS training stage set to `n` steps (None: unchanged)."""
        if n is None:
            return self
        return replace(self, iters_refgs=n, iters_ted_finetune=n, iters_ted_adversarial=n)
