"""Stage 1, initial 2D inpainting (paper 4.1): one inpainted image I^_n per training view with a mask.

Source, in order (the first available, named in the log and in `sources.json`):
1. Stable Diffusion 2 inpainting from a local folder (`sd_path` / COIN_SD2_PATH), 512 crops;
2. the dataset's own per-view inpaints (SPIn-NeRF's LaMa `RGB_inpainted/`), only for "seg" masks:
   they were made for the object's segmentation and do not cover a bounding box or scribbles;
3. the embedded "scene prior" (a small inpainting UNet trained here on the scene's own pixels
   outside every mask; `coin_cl.diffusion.scene_prior`), saved in the stage folder for CLG;
4. OpenCV's classical inpainting, when the prior is switched off.
Views without a mask keep their captured image (logged).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from coin_cl.diffusion.inpaint2d import InpaintConfig, inpaint_image
from coin_cl.diffusion.scene_prior import ScenePriorConfig, steps_for_seconds, train_scene_prior
from coin_cl.scene.io import read_image, to_uint8, write_png

log = logging.getLogger(__name__)


@dataclass
class Inpaint2DConfig:
    """use_dataset: take the dataset's per-view inpaints when they exist (seg masks only).
    use_prior: train and use the scene prior (else OpenCV when there is no SD2 and no dataset
    inpaint). prior: the scene prior's settings (its time budget is scaled by the pipeline).
    inpaint: crop/paste/sampler settings. seed: an offset to the run's seed for sampling (view n
    uses run seed + seed + n)."""

    use_dataset: bool = True
    use_prior: bool = True
    prior: ScenePriorConfig = field(default_factory=ScenePriorConfig)
    inpaint: InpaintConfig = field(default_factory=InpaintConfig)
    seed: int = 0


def effective_config(
    cfg: Inpaint2DConfig, prior_seconds: float, seed: int, width: int, height: int
) -> Inpaint2DConfig:
    """The settings stage 1 really uses (and CLG must repeat to find its cached prior): the
    pipeline's time budget (as a step count, `steps_for_seconds`) and seed, and a working patch no
    larger than the images (the largest multiple of 8 that fits, at least 16)."""
    patch = max(16, min(cfg.prior.patch, (min(width, height) // 8) * 8))
    if patch != cfg.prior.patch:
        log.info(
            "1_inpaint: scene prior patch %d -> %d to fit %dx%d images", cfg.prior.patch, patch, width, height
        )
    # A step count, not the seconds themselves: the same prior on any machine, and a killed run
    # resumes to it (an explicit `prior.train_steps` wins).
    steps = cfg.prior.train_steps if cfg.prior.train_steps is not None else steps_for_seconds(prior_seconds)
    prior = replace(cfg.prior, train_seconds=prior_seconds, train_steps=steps, seed=seed, patch=patch)
    # The run's seed reaches stage 1's sampling too: `cfg.seed` is an offset to it.
    return replace(cfg, prior=prior, seed=seed + cfg.seed)


def stage_prior(scene, masks: list[np.ndarray], views: list[int], cfg: Inpaint2DConfig, folder: Path):
    """The scene prior of this stage: trained on the pixels outside every mask of `views`, cached in
    `folder` by a hash of images, masks and settings (so CLG reloads the one stage 1 trained)."""
    return train_scene_prior(
        [scene.images[i] for i in views], [masks[i] for i in views], cfg.prior, cache_dir=folder
    )


def run_inpaint2d(
    scene,
    masks: list[np.ndarray],
    views: list[int],
    out_dir: Path,
    cfg: Inpaint2DConfig,
    mask_kind: str = "seg",
    sd2=None,
    prompt: str = "",
) -> dict:
    """Inpaint `views` of `scene` in `masks`; writes `images/<name>.png` and `sources.json`.

    Resumable: a view whose image exists is not redone. Returns {"sources": the sources used (sorted
    names; per view in `sources.json`), "prior": {...} or None}.
    """
    out_dir = Path(out_dir)
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    dataset = scene.priors.get("rgb", {}) if (cfg.use_dataset and mask_kind == "seg" and sd2 is None) else {}
    if cfg.use_dataset and mask_kind != "seg" and scene.priors.get("rgb"):
        log.info("1_inpaint: the dataset's inpaints cover seg masks only; not used for %s masks", mask_kind)
    todo = [i for i in views if masks[i].any() and i not in dataset and sd2 is None]
    prior, prior_info = None, None
    if todo and cfg.use_prior:
        prior = stage_prior(scene, masks, views, cfg, out_dir)
        prior_info = {"name": "scene prior (embedded default replacing Stable Diffusion 2)",
                      "steps": getattr(prior, "info", {}).get("steps")}  # fmt: skip
    sources: dict[str, str] = {}
    for i in views:
        name = Path(scene.cameras[i].name).stem + ".png"
        path = img_dir / name
        if path.is_file():
            sources[name] = "(kept from an earlier run)"
            continue
        if not masks[i].any():
            sources[name] = "captured image (no mask)"
            write_png(path, to_uint8(scene.images[i]))
            continue
        img, src = inpaint_image(
            scene.images[i], masks[i], sd2=sd2, dataset_inpaint=dataset.get(i), scene_prior=prior,
            cfg=cfg.inpaint, prompt=prompt, seed=cfg.seed + i,
        )  # fmt: skip
        sources[name] = src
        write_png(path, to_uint8(img))
    old = out_dir / "sources.json"
    if old.is_file():
        sources = {
            **json.loads(old.read_text()),
            **{k: v for k, v in sources.items() if not v.startswith("(")},
        }
    old.write_text(json.dumps(sources, indent=1, sort_keys=True))
    names = sorted(set(sources.values()))
    log.info("1_inpaint: sources used: %s", ", ".join(names))
    return {"sources": names, "prior": prior_info}


def read_inpaints(scene, folder: Path, views: list[int]) -> dict[int, np.ndarray]:
    """{view: I^_n (H, W, 3) float32} written by `run_inpaint2d`."""
    out = {}
    for i in views:
        p = Path(folder) / "images" / (Path(scene.cameras[i].name).stem + ".png")
        if not p.is_file():
            raise FileNotFoundError(f"{p} missing: rerun stage 1_inpaint")
        out[i] = read_image(p)
    return out
