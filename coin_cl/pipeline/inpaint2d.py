"""Stage 1, initial 2D inpainting (paper 4.1): one inpainted image I^_n per training view with a mask.

Source, in order (the first available, named in the log and in `sources.json`):
1. Stable Diffusion 2 inpainting from a local folder (`sd_path` / COIN_SD2_PATH), 512 crops (the
   run's cost estimate is logged first, `coin_cl.diffusion.sd2.log_sd2_estimate`);
2. the dataset's own per-view inpaints (SPIn-NeRF's LaMa `RGB_inpainted/`), only for "seg" masks:
   they were made for the object's segmentation and do not cover a bounding box or scribbles;
3. `Inpaint2DConfig.inpainter`: "auto" (default) is LaMa when a TorchScript file is named
   (`lama_path` / COIN_LAMA_PATH), else the embedded exemplar inpainter; "embedded" the exemplar
   inpainter (`coin_cl.diffusion.exemplar`: smooth structure + exemplar patches of this view and its
   `exemplar_views` neighbours, at the hole's resolution); "lama" LaMa (an error without the file);
   "prior" the scene prior (a small UNet trained on the scene's pixels, the earlier default); "telea"
   OpenCV's classical inpainting.
   The rule behind "auto" is measured (benchmarks/inpaint2d.py, docs/BENCHMARKS.md): on held-out holes
   the exemplar fill has lower GMSD and SWD than Telea and FSR at about 1 dB m-PSNR less, where the
   scene prior scored 4.8 dB below Telea with an HF ratio of 1.8 (noise).
Views without a mask keep their captured image (logged).
"""

from __future__ import annotations

import json
import logging
import os
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coin_cl.diffusion.exemplar import EXEMPLAR_NAME, ExemplarConfig, exemplar_inpaint
from coin_cl.diffusion.inpaint2d import InpaintConfig, inpaint_image, paste
from coin_cl.diffusion.lama import LAMA_ENV, LAMA_NAME, lama_inpaint, load_lama
from coin_cl.diffusion.scene_prior import ScenePriorConfig, steps_for_seconds, train_scene_prior
from coin_cl.scene.io import read_image, to_uint8, write_png, write_text
from coin_cl.schema import INPAINT_SOURCES, parse_optional, run_folder_fix

if TYPE_CHECKING:
    from coin_cl.pipeline.budget import Plan

log = logging.getLogger(__name__)


@dataclass
class Inpaint2DConfig:
    """Stage 1's settings (module docstring); each field says what it means where it is declared."""

    # Take the dataset's per-view inpaints when they exist (seg masks only). Default True: they are
    # the paper's inputs (SPIn-NeRF's LaMa inpaints).
    use_dataset: bool = True
    # What fills views without SD2 or dataset inpaints, from INPAINTERS (module docstring). Default
    # "auto": LaMa when a file is named, else the embedded exemplar inpainter (measured better).
    inpainter: str = "auto"
    # The TorchScript big-lama.pt. None (default): $COIN_LAMA_PATH. TorchScript runs as code, so it
    # is trusted input, never a file from just anyone.
    lama_path: str | None = None
    # The embedded exemplar inpainter's settings (`diffusion.exemplar`).
    exemplar: ExemplarConfig = field(default_factory=ExemplarConfig)
    # Neighbouring views (by index, nearest first) the exemplar inpainter copies patches from besides
    # the view itself (>= 0). Default 4.
    exemplar_views: int = 4
    # With inpainter "prior": train and use the scene prior (False: OpenCV's Telea). Default True.
    use_prior: bool = True
    # The scene prior's settings. A CoIn run sets its train_seconds (from `CoInConfig.prior_seconds`),
    # train_steps (the plan's, unless given here), seed (the run's) and a patch that fits the
    # images (`effective_config`); CoInConfig refuses a train_seconds or seed set here.
    prior: ScenePriorConfig = field(default_factory=ScenePriorConfig)
    # Crop / paste / sampler settings (`diffusion.inpaint2d`).
    inpaint: InpaintConfig = field(default_factory=InpaintConfig)
    # An offset to the run's seed for sampling (view n uses run seed + seed + n). Default 0.
    seed: int = 0
    # With SD2 weights, from `models.SD2_MODES`: "all" (SD2 on every view, as the paper),
    # "reference_only" (SD2 on the reference; the other views take `inpainter` and CLG warps the
    # reference: the CPU-practical mode) or "auto" (default: "reference_only" on a CPU when the
    # estimate for "all" exceeds `models.SD2_ALL_VIEWS_MAX_HOURS`, logged with the estimate).
    sd2_mode: str = "auto"
    # With refined masks (stage 0_refine), what the inpainter sees around a view's unseen core, from
    # CONTEXTS: "captures" (default: the captured photo with the whole input mask as the hole, so
    # the fill continues the real surroundings; it is kept in the unseen core only) or "split" (the
    # split's image: the object-free fit's render in the observed part around the core, supplement
    # C.2 as written). Measured on cup_plain's 56 training views against the photo behind the
    # virtual box, the embedded inpainter after a 10-minute run's split: unseen core 25.46 dB
    # against 22.59 (the render around it was 19.8 dB there, a grey wash the fill continued).
    context: str = "captures"
    # Views the embedded exemplar inpainter fills at once, each in its own thread (numpy's gathers
    # and OpenCV's solvers release the interpreter's lock). 0 (default): one per core this process
    # may use. A view's fill depends on its own seed alone, so every count gives the same images;
    # it is not part of the stage's rerun key.
    workers: int = 0

    def __post_init__(self) -> None:
        from coin_cl.pipeline.models import SD2_MODES

        if self.context not in CONTEXTS:
            raise ValueError(f"Inpaint2DConfig.context must be one of {', '.join(CONTEXTS)}, "
                             f"got {self.context!r}")  # fmt: skip

        if self.inpainter not in INPAINTERS:
            raise ValueError(f"Inpaint2DConfig.inpainter must be one of {', '.join(INPAINTERS)}, "
                             f"got {self.inpainter!r}")  # fmt: skip
        if self.sd2_mode not in SD2_MODES:
            raise ValueError(f"Inpaint2DConfig.sd2_mode must be one of {', '.join(SD2_MODES)}, "
                             f"got {self.sd2_mode!r}")  # fmt: skip
        if not (isinstance(self.exemplar_views, int) and self.exemplar_views >= 0):
            raise ValueError(f"Inpaint2DConfig.exemplar_views is {self.exemplar_views!r}: give an "
                             "integer >= 0")  # fmt: skip
        if not (isinstance(self.workers, int) and self.workers >= 0):
            raise ValueError(
                f"Inpaint2DConfig.workers is {self.workers!r}: give an integer >= 0 (0: one per core)"
            )
        if self.lama_path is not None and not Path(self.lama_path).expanduser().is_file():
            # Checked even where the scene's own inpaints make LaMa unneeded: a mistyped path is
            # said at once, not found out at the run that needs it.
            raise ValueError(f"--lama-path / lama_path {self.lama_path!r}: no such file; give the path of "
                             "LaMa's TorchScript big-lama.pt or leave it out")  # fmt: skip


INPAINTERS = ("auto", "embedded", "lama", "prior", "telea")
CONTEXTS = ("captures", "split")  # Inpaint2DConfig.context


def resolve_inpainter(cfg: Inpaint2DConfig) -> str:
    """The inpainter "auto" stands for: "lama" when a LaMa file is named, else "embedded"."""
    if cfg.inpainter != "auto":
        return cfg.inpainter
    return "lama" if (cfg.lama_path or os.environ.get(LAMA_ENV)) else "embedded"


# Stage-1 sources that draw texture the way a photograph has it (a learned inpainter's), as opposed
# to the embedded ones: the exemplar inpainter's collage of the scene's patches, Telea's smooth fill,
# the scene prior's noise.
GENERATIVE_SOURCES = ("sd2", "dataset", "lama")


def fill_source(scene, cfg: Inpaint2DConfig, mask_kind: str, sd_path: str | None) -> str:
    """What stage 1 will fill most views with, known before it runs: "sd2" (weights named),
    "dataset" (the scene's own per-view inpaints, seg masks), else `resolve_inpainter`'s choice."""
    if sd_path:
        return "sd2"
    if cfg.use_dataset and mask_kind == "seg" and scene.priors.get("rgb"):
        return "dataset"
    return resolve_inpainter(cfg)


def rerun_key(cfg: Inpaint2DConfig) -> dict:
    """Stage 1's settings as its rerun key: the config, plus the LaMa file the run really reads when
    the inpainter resolves to LaMa (`lama_path`, else $COIN_LAMA_PATH: pointing the variable at
    another file must rerun the stage) with its size and modification time (the same path holding a
    new file reruns it too)."""
    from coin_cl.pipeline.runner import jsonable

    key = {"cfg": {k: v for k, v in jsonable(cfg).items() if k != "workers"}}  # same fills at any count
    if resolve_inpainter(cfg) == "lama":
        src = cfg.lama_path or os.environ.get(LAMA_ENV)
        p = Path(src).expanduser() if src else None
        st = p.stat() if p is not None and p.is_file() else None
        key["lama"] = {
            "path": str(p.resolve()) if p is not None else None,
            "bytes": st.st_size if st else None,
            "mtime_ns": st.st_mtime_ns if st else None,
        }
    return key


def prior_key(cfg: Inpaint2DConfig, prior_seconds: float, prior_steps: int | None) -> dict:
    """What stage 1's rerun key holds of the plan's scene prior: its seconds and measured steps
    where stage 1 trains the prior (inpainter "prior"), else nothing: no other fill depends on them,
    so a comparison row planned differently (a naive row's explicit plan) reuses the fills."""
    if resolve_inpainter(cfg) != "prior" or not cfg.use_prior:
        return {}
    # the measured step count (plans made before it have none: their key is unchanged)
    steps = {} if prior_steps is None else {"prior_steps": prior_steps}
    return {"prior_seconds": prior_seconds, **steps}


def fill_workers(cfg: Inpaint2DConfig) -> int:
    """The threads filling views at once: `cfg.workers`, or one per core this process may use."""
    if cfg.workers:
        return cfg.workers
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count() or 1)
    return max(1, len(cores))


def neighbour_views(i: int, views: list[int], k: int) -> list[int]:
    """Up to k views of `views` other than i, nearest in index first (captures are ordered)."""
    return sorted((j for j in views if j != i), key=lambda j: (abs(j - i), j))[:k]


def effective_config(
    cfg: Inpaint2DConfig,
    prior_seconds: float,
    seed: int,
    width: int,
    height: int,
    prior_steps: int | None = None,
) -> Inpaint2DConfig:
    """The settings stage 1 really uses (and CLG must repeat to find its cached prior): the
    pipeline's time budget as a step count (`prior_steps`, the plan's figure measured on this
    machine, else `steps_for_seconds` at the fixed 2-core rate) and seed, and a working patch no
    larger than the images (the largest multiple of 8 that fits, at least 16)."""
    patch = max(16, min(cfg.prior.patch, (min(width, height) // 8) * 8))
    if patch != cfg.prior.patch:
        log.info(
            "1_inpaint: scene prior patch %d -> %d to fit %dx%d images", cfg.prior.patch, patch, width, height
        )
    # A step count, not the seconds themselves: the same prior on any machine, and a killed run
    # resumes to it (an explicit `prior.train_steps` wins).
    steps = cfg.prior.train_steps
    if steps is None:
        steps = prior_steps if prior_steps is not None else steps_for_seconds(prior_seconds)
    prior = replace(cfg.prior, train_seconds=prior_seconds, train_steps=steps, seed=seed, patch=patch)
    # The run's seed reaches stage 1's sampling too: `cfg.seed` is an offset to it.
    return replace(cfg, prior=prior, seed=seed + cfg.seed)


def planned_config(cfg: Inpaint2DConfig, plan: Plan, seed: int, width: int, height: int) -> Inpaint2DConfig:
    """`effective_config` with the run's plan (its prior_seconds and, where measured, prior_steps),
    the one stage 1 and CLG both build (CLG must find the prior stage 1 trained)."""
    return effective_config(cfg, plan.prior_seconds, seed, width, height, plan.prior_steps)


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
    sd2_views: list[int] | None = None,
    sd2_why: str = "",
    exact_masks: bool = False,
    context: tuple[list[np.ndarray], list[np.ndarray]] | None = None,
) -> dict:
    """Inpaint `views` of `scene` in `masks`; writes `images/<name>.png` and `sources.json`.

    context: (images, holes) per scene view that the inpainter works on instead of the scene's own
    (`Inpaint2DConfig.context` "captures": the captured photos and the input masks, which hold
    `masks`); its fill then replaces the scene's image inside `masks` only.

    exact_masks: the masks end at the object's edge (not dilated beyond it, or refined cores whose
    captured pixels are the object): a pasted fill is feathered toward the surroundings continued
    inward, not toward the masked pixels (`diffusion.inpaint2d.paste`'s edge).

    sd2_views: with `sd2`, the views SD2 inpaints (None: all; SD2's CPU-practical mode passes the
    reference only, the rest take `cfg.inpainter`); the choice and `sd2_why` go to `sd2.json`,
    which CLG follows.

    Resumable: a view whose image exists is not redone. Returns {"sources": the sources used (sorted
    names; per view in `sources.json`), "prior": {...} or None}.
    """
    out_dir = Path(out_dir)
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    dataset = scene.priors.get("rgb", {}) if (cfg.use_dataset and mask_kind == "seg" and sd2 is None) else {}
    if cfg.use_dataset and mask_kind != "seg" and scene.priors.get("rgb"):
        log.info("1_inpaint: the dataset's inpaints cover seg masks only; not used for %s masks", mask_kind)
    by_sd2 = set() if sd2 is None else set(views if sd2_views is None else sd2_views)
    todo = [i for i in views if masks[i].any() and i not in dataset and i not in by_sd2]
    kind = resolve_inpainter(cfg)
    edge = "surroundings" if exact_masks else "image"
    prior, prior_info, lama = None, None, None
    if sd2 is not None:
        from coin_cl.diffusion.sd2 import log_sd2_estimate

        n_sd2 = sum(bool(masks[i].any()) for i in by_sd2)
        log_sd2_estimate(n_sd2, cfg.inpaint.sampler_sd.num_steps, None if sd2_views is None else 0)
        mode = "all" if sd2_views is None else "reference_only"
        names = sorted(Path(scene.cameras[i].name).stem for i in by_sd2)
        write_text(out_dir / "sd2.json", json.dumps({"mode": mode, "views": names, "why": sd2_why}, indent=1))
    if todo and kind == "prior" and cfg.use_prior:
        prior = stage_prior(scene, masks, views, cfg, out_dir)
        prior_info = {"name": "scene prior (embedded default replacing Stable Diffusion 2)",
                      "steps": getattr(prior, "info", {}).get("steps")}  # fmt: skip
    if todo and kind == "lama":
        lama = load_lama(cfg.lama_path)
    if todo:
        log.info("1_inpaint: %d views without SD2 or dataset inpaints use the %s inpainter", len(todo), kind)
    sources: dict[str, str] = {}
    record = out_dir / "sources.json"
    # Recorded view by view, before its image: a killed run's resumption keeps each finished view's
    # source (a kill between the two redoes the view).
    done: dict[str, str] = (
        parse_optional(record, INPAINT_SOURCES, run_folder_fix(record, "stage 1 runs again")) or {}
    )

    def note(name: str, src: str) -> None:
        sources[name] = done[name] = src
        write_text(record, json.dumps(done, indent=1, sort_keys=True))

    from tqdm import tqdm

    image, hole = (scene.images, masks) if context is None else context  # what the inpainter sees

    def exemplar(i: int) -> np.ndarray:
        src = [(image[j], hole[j]) for j in neighbour_views(i, views, cfg.exemplar_views)]
        return exemplar_inpaint(image[i], hole[i], cfg.exemplar, seed=cfg.seed + i, sources=src)

    def path_of(i: int) -> Path:
        return img_dir / (Path(scene.cameras[i].name).stem + ".png")

    # The exemplar fills run ahead in threads, at most two per worker waiting, and are written in
    # view order by this thread (so a killed run resumes from the same finished views).
    queue = [i for i in views if i in todo and kind == "embedded" and not path_of(i).is_file()]
    workers = min(fill_workers(cfg), max(1, len(queue)))
    pool = (
        ThreadPoolExecutor(workers, thread_name_prefix="exemplar") if len(queue) > 1 and workers > 1 else None
    )
    ahead: dict[int, Future] = {}

    def fill_of(i: int) -> np.ndarray:
        if pool is None:
            return exemplar(i)
        while queue and len(ahead) < 2 * workers:
            j = queue.pop(0)
            ahead[j] = pool.submit(exemplar, j)
        return ahead.pop(i).result()

    if pool is not None:
        log.info("1_inpaint: the exemplar inpainter fills %d views, %d at a time", len(queue), workers)
    try:
        # a bar per view: the exemplar inpainter takes about a second a view, LaMa and SD2 much longer
        for i in tqdm(views, desc="stage 1 inpaint", unit="view"):
            path = path_of(i)
            name = path.name
            if path.is_file():
                sources[name] = done.get(name, "(kept from an earlier run)")
                continue
            if not masks[i].any():
                note(name, "captured image (no mask)")
                write_png(path, to_uint8(scene.images[i]))
                continue
            if i in todo and kind == "embedded":
                img, src = fill_of(i), EXEMPLAR_NAME
            elif i in todo and kind == "lama":
                fill = lama_inpaint(lama, image[i], hole[i])
                img, src = paste(image[i], fill, hole[i], cfg.inpaint.feather_px, edge), LAMA_NAME
            else:
                img, src = inpaint_image(
                    image[i], hole[i], sd2=sd2 if i in by_sd2 else None, dataset_inpaint=dataset.get(i),
                    scene_prior=prior,
                    cfg=cfg.inpaint, prompt=prompt, seed=cfg.seed + i, edge=edge,
                )  # fmt: skip
            if context is not None:
                img = np.where(np.asarray(masks[i], bool)[..., None], img, scene.images[i])
            note(name, src)
            write_png(path, to_uint8(img))
    finally:
        if pool is not None:  # an error or Ctrl-C: the views not started are dropped
            pool.shutdown(wait=True, cancel_futures=True)
    sources = {**done, **sources}
    write_text(record, json.dumps(sources, indent=1, sort_keys=True))
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
