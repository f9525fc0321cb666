"""What every CoIn stage is given: `RunInputs`, built once by `coin_cl.pipeline.coin` before the
first stage and carried by the runner (`StageContext.run`) to each stage function unchanged.

A stage's own results travel as files between stage folders (the runner's manifests hash them); what
is here is what the run was asked for, resolved: nothing a stage computes is written back into it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.pipeline.budget import Plan
    from coin_cl.pipeline.config import CoInConfig
    from coin_cl.scene import Scene
    from coin_cl.scene.types import Camera


@dataclass(frozen=True)
class CaptureViews:
    """The object-absent test views with a mask at the capture's own resolution, kept from the scene
    before it is resized to the working resolution: {scene view index: camera / (H, W, 3) float32
    image in [0, 1] / (H, W) bool mask}."""

    cameras: dict[int, Camera]
    images: dict[int, np.ndarray]
    masks: dict[int, np.ndarray]


def capture_views(scene: Scene) -> CaptureViews | None:
    """`CaptureViews` of `scene` at its loaded resolution; None when no test view has a mask."""
    idx = [i for i in scene.test_idx if np.asarray(scene.masks[i]).any()]
    if not idx:
        return None
    return CaptureViews({i: scene.cameras[i] for i in idx}, {i: scene.images[i] for i in idx},
                        {i: np.asarray(scene.masks[i], bool) for i in idx})  # fmt: skip


@dataclass(frozen=True)
class RunInputs:
    """The run's inputs (frozen: a stage reads them, never replaces one). The arrays and the scene
    are shared with the caller, not copied: stages copy what they change (`dataclasses.replace`)."""

    # The run folder (TE-D's schedule reads the Ref-GS rate recorded under it: `schedule.ted_schedule`).
    out: Path
    # The scene at the working resolution, its masks as given (before `masks` below derives from them).
    scene: Scene
    # Per scene view, the (H, W) bool training mask: `CoInConfig.mask_kind` of the given one, dilated.
    masks: list[np.ndarray]
    # The reference view's scene index (the view CLG warps from and Ref-GS trains around).
    ref: int
    # The run's settings, resolved (mask dilation, inpaint region): the values the stage keys hold.
    cfg: CoInConfig
    # Step counts, the scene prior's training and the time caps (`budget.Plan`, OUT/plan.json).
    plan: Plan
    # Ref-GS's settings around `ref` (`CoInConfig.refgs_settings`).
    refgs_cfg: RefGSConfig
    # An insertion's edited reference view, (H, W, 3) float32 in [0, 1] at the working size
    # (`insert.load_edited`); None for a removal.
    edited: np.ndarray | None = None
    # The object-absent test views at the capture's resolution, where the working resolution is
    # smaller (the eval stage scores them too); None otherwise.
    capture: CaptureViews | None = None
