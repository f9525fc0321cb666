"""The run's settings: `CoInConfig`, everything `coin_cl.pipeline.coin.inpaint` takes beyond the scene,
with the settings of each stage it holds (`Inpaint2DConfig`, `RefGSConfig`, `CLGConfig`, `TEDConfig`,
...). Its own module so that the stage functions (`stages`, `eval_stage`) read the type without
importing the module that builds the stage graph; `coin_cl.pipeline.coin` re-exports it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

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


@dataclass
class CoInConfig:
    """mask_kind: the shape of mask given for the object, "seg" | "bbox" | "scribble" (the latter two
    derived from the scene's segmentation masks).
    mask_dilate: iterations of a 5x5 dilation of the training masks (2 px each); None (default) = a
    ring of `scene.masks.MASK_RING_SHARE` (1.4 %) of the longer side at the working size, as
    SPIn-NeRF's masks (8 px at 504x284): the object's fringe and contact shadow left outside the
    mask are trained as background (the box's edges stayed as thin lines without it); but none
    for a scene whose scene_info.json declares its masks exact (the synthetic rooms: there the
    ring cost the part of the masks other views saw 1 dB, docs/RESULTS.md "Where the rooms'
    m-PSNR is decided"); 0 = as given. Below the ring, the refined split's removal vote still
    takes the ring (`refine_masks.vote_ring`).
    ref: reference view (index or name); None chooses by `coin_cl.pipeline.reference.choose_reference`.
    prompt: text for insertion (needs SD2 weights). budget_minutes: total training time to aim at.
    resolution: image scale (0.5 = half); None picks it from the image size
    (`coin_cl.pipeline.budget.working_resolution`, logged). sd_path / dino_path: local weights (else
    the embedded defaults, named in the log). skip: stage keys to leave out ("refgs", "clg", "ted").
    iters_*, prior_seconds: explicit iteration counts and the scene prior's training seconds (each
    replaces the budget plan's figure; see `coin_cl.pipeline.budget`; TE-D's counts may also be
    given as `ted.iters_*`, and where both are set they must agree). seed, device: as everywhere.
    edited_ref: path of the reference view edited by the user (insertion without weights,
    `coin_cl.pipeline.insert`); `inpaint(edited_ref=...)` also takes an array. insert: its settings.
    inpaint_region: "input" (inpaint the whole masks), "refined" (3D-first, supplement C.2: stage
    0_refine narrows them to the pixels no other view sees, `coin_cl.pipeline.refine_masks`; for
    removal on wide captures) or "auto" (removal: "refined" when the cheap estimate
    `coin_cl.gs.carve.observed_share` finds at least AUTO_REFINE_SHARE of the masks seen by other
    views, else "input"; logged with its figure). refine: its settings.
    carve: removal carves the object's volume out of the GS for good (`coin_cl.gs.carve`: what the
    masks cut out of space in front of the background surface gets no Gaussian, in Ref-GS, TE-D
    and the exported model) and seeds anchors on the background behind it; not with insertion or
    the naive / w/o Ref-GS rows. Off by default: measured at 400 Ref-GS steps it cost SPIn-NeRF
    0.7 dB m-PSNR (13.16 against 13.87), texture (HF ratio 0.41 against 0.49) and GMSD, and on
    the synthetic room it gained 1.1 dB m-PSNR but blurred (docs/RESULTS.md, issue 21).
    carve_cfg: its settings.
    observed: how the observed part of a refined mask (0_refine's split) reaches the model:
    "captures" (default: left out of view n's photometric loss in Ref-GS and TE-D, so the other
    views' captures teach it, as masked reconstruction does; R^rmv_n stays the 2D inpainter's and
    CLG's context) or "target" (the object-free fit's render R^rmv_n is view n's target there).
    Measured at 1501 GS steps with the rooms' exact masks, "captures" against "target" (one
    machine): room m-PSNR 22.44 / 22.25, HF ratio 0.793 / 0.780, GMSD 0.140 / 0.139; room360
    22.49 / 22.44, 0.906 / 0.862, 0.137 / 0.142 (docs/RESULTS.md, "The observed part from the
    captures by default").
    Only refined-mask runs read it.
    rates_from: a run folder whose plan's measured rates (the GS, scene-prior and discriminator
    probes) this run's plan takes instead of probing again (`budget.inherited_rates`): the
    comparison rows (`demo.baseline_config`) plan with CoIn's figures and share its stages."""

    mask_kind: str = "seg"
    mask_dilate: int | None = None
    ref: int | str | None = None
    prompt: str = ""
    budget_minutes: float = 30.0
    resolution: float | None = None
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
    refgs: RefGSConfig | None = None  # None: RefGSConfig() with the run's reference
    clg: CLGConfig | None = None  # None: CLGConfig()
    edited_ref: str | None = None
    insert: InsertConfig = field(default_factory=InsertConfig)
    inpaint_region: str = "auto"
    refine: RefineConfig = field(default_factory=RefineConfig)
    carve: bool = False
    carve_cfg: CarveConfig = field(default_factory=CarveConfig)
    observed: str = "captures"
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

    def with_iters(self, n: int | None) -> CoInConfig:
        """This config with every GS training stage set to `n` steps (None: unchanged)."""
        if n is None:
            return self
        return replace(self, iters_refgs=n, iters_ted_finetune=n, iters_ted_adversarial=n)
