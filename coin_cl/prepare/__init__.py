"""From a folder of photos to a scene coin-cl runs on: structure from motion (`sfm`) and object
masks from one annotation (`annotate`, `propagate`, `scene_masks`). Weight-free: pycolmap and
OpenCV's GrabCut; a user's segmenter (SAM) plugs in as `segment` (`propagate.Segmenter`)."""

from __future__ import annotations

from pathlib import Path

from .propagate import PropagateConfig, PropagateResult, Segmenter, propagate_masks
from .scene_masks import Annotation, make_masks
from .sfm import SfmConfig, run_sfm
from .sfm_report import SfmReport, read_report

__all__ = [
    "Annotation",
    "PropagateConfig",
    "PropagateResult",
    "Segmenter",
    "SfmConfig",
    "SfmReport",
    "make_masks",
    "prepare",
    "propagate_masks",
    "read_report",
    "run_sfm",
]


def prepare(
    photos_dir: str | Path,
    scene_dir: str | Path,
    annotation: Annotation | None = None,
    sfm: SfmConfig | None = None,
    masks: PropagateConfig | None = None,
    segment: Segmenter | None = None,
    holdout: list[str] | tuple[str, ...] = (),
    holdout_masks: str | Path | None = None,
) -> tuple[SfmReport, PropagateResult | None]:
    """Photos -> `scene_dir` (plain COLMAP layout that `coin_cl.load_scene` reads) and, given an
    annotation of the object in one view, its masks in every view. A box in the annotation is in
    the photo's pixels (scaled here to the working size). Resumes what a previous run left.
    holdout: photos posed but not trained on (test views, `holdout.py`); holdout_masks: a folder
    with their region masks drawn on the photos (<stem>.png), written to masks/."""
    if holdout_masks is not None and not holdout:
        raise ValueError("--holdout-masks needs --holdout: name the held-out photos")
    if holdout_masks is not None and annotation is None:
        # the loader would find masks/ without the training views' masks
        raise ValueError(
            "--holdout-masks needs an annotation of the object (--box, --scribble or --mask): the "
            "training views need their masks beside the held-out ones"
        )
    report = run_sfm(photos_dir, scene_dir, sfm, holdout)
    if holdout_masks is not None and report.held_out:
        from ..scene.colmap import read_cameras
        from .holdout import write_holdout_masks
        from .sfm import WORK

        cam = next(iter(read_cameras(Path(scene_dir) / WORK / "sparse" / "best").values()))
        write_holdout_masks(Path(scene_dir), sorted(report.held_out), Path(holdout_masks), cam)
    if annotation is None:
        return report, None
    if annotation.box is not None and annotation.photos_dir is None:
        annotation.photos_dir = Path(photos_dir)
    return report, make_masks(scene_dir, annotation, masks, segment)
