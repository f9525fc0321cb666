"""CoIn's 2D branch in CPU torch: DDIM sampling with energy guidance, Stable Diffusion 2 inpainting from
local weights, LaMa from a local TorchScript file, the embedded exemplar inpainter and scene prior,
feature extractors and the TE-D patch discriminator.

This package never imports OpenCL or the engine; the pipeline joins the two. Inside it, imports are
relative so it can move under another package.
"""

from __future__ import annotations

import os

# torch's OpenMP threads spin while idle unless told otherwise, which starves OpenCL kernels on the same
# cores (measured: a small UNet forward 37 ms -> 200-4,700 ms); must be set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .analytic import GaussianDenoiser  # noqa: E402
from .discriminator import (  # noqa: E402
    PatchDiscriminator,
    PatchGANConfig,
    crop_patches,
    d_loss,
    g_loss,
    sample_patch_corners,
)
from .exemplar import EXEMPLAR_NAME, ExemplarConfig, exemplar_inpaint  # noqa: E402
from .features import (  # noqa: E402
    ANALYTIC_NAME,
    DINO_ENV,
    DINO_NAME,
    AnalyticFeatureConfig,
    AnalyticFeatures,
    DinoFeatures,
    joint_bilateral_upsample,
    load_dino,
    make_feature_extractor,
)
from .inpaint2d import InpaintConfig, inpaint_image, opencv_inpaint  # noqa: E402
from .lama import LAMA_ENV, lama_inpaint, load_lama  # noqa: E402
from .sampling import (  # noqa: E402
    DDIMSampler,
    Denoiser,
    FunctionDenoiser,
    SamplerConfig,
    SampleResult,
    split_prediction,
)
from .scene_prior import ScenePrior, ScenePriorConfig, train_scene_prior  # noqa: E402
from .schedule import ScheduleConfig, alphas_cumprod, ddim_timesteps  # noqa: E402
from .sd2 import ENV_VAR as SD2_ENV  # noqa: E402
from .sd2 import SD2Denoiser, check_sd2_folder, missing_sd2_files, resolve_sd2_path  # noqa: E402


def available_models(
    sd2_path: str | os.PathLike | None = None,
    dino_path: str | os.PathLike | None = None,
    prior_cache_dir: str | os.PathLike | None = None,
) -> dict[str, dict]:
    """Which 2D models can run here, and why (for ``coin-cl doctor``). Loads nothing heavy.

    Returns {'sd2': ..., 'lama': ..., 'dino': ..., 'scene_prior': ...}, each {'available': bool,
    'reason': str} plus 'path' where one is known. The scene prior is always available (trained on
    the scene at run time); the reason says whether cached models exist in prior_cache_dir.
    """
    out: dict[str, dict] = {}
    p = resolve_sd2_path(sd2_path)
    if p is None:
        out["sd2"] = {"available": False, "reason": f"{SD2_ENV} not set and no --sd-path given"}
    else:
        missing = missing_sd2_files(p)
        src = "--sd-path" if sd2_path is not None else SD2_ENV
        out["sd2"] = {
            "available": not missing,
            "path": str(p),
            "reason": f"{src}={p}: "
            + ("complete diffusers folder" if not missing else f"missing {', '.join(missing)}"),
        }
    lp = os.environ.get(LAMA_ENV)
    if not lp:
        out["lama"] = {"available": False, "reason": f"{LAMA_ENV} not set (--lama-path at run time)"}
    else:
        ok = os.path.isfile(lp)
        out["lama"] = {
            "available": ok,
            "path": lp,
            "reason": f"{LAMA_ENV}={lp} " + ("found" if ok else "does not exist"),
        }
    dp = dino_path if dino_path is not None else os.environ.get(DINO_ENV)
    if not dp:
        out["dino"] = {
            "available": False,
            "reason": f"{DINO_ENV} not set; the {ANALYTIC_NAME} are used instead",
        }
    else:
        ok = os.path.isfile(dp)
        out["dino"] = {
            "available": ok,
            "path": str(dp),
            "reason": f"weights file {dp} " + ("found" if ok else "does not exist"),
        }
    reason = "embedded: trained on the scene's own images at run time (minutes on the CPU)"
    if prior_cache_dir is not None:
        from pathlib import Path

        n = len(list(Path(prior_cache_dir).glob("scene_prior_*.pt"))) if Path(prior_cache_dir).is_dir() else 0
        reason += f"; {n} cached model(s) in {prior_cache_dir}"
    out["scene_prior"] = {"available": True, "reason": reason}
    return out


__all__ = [
    "ANALYTIC_NAME",
    "EXEMPLAR_NAME",
    "LAMA_ENV",
    "ExemplarConfig",
    "exemplar_inpaint",
    "lama_inpaint",
    "load_lama",
    "DINO_ENV",
    "DINO_NAME",
    "SD2_ENV",
    "AnalyticFeatureConfig",
    "AnalyticFeatures",
    "DDIMSampler",
    "Denoiser",
    "DinoFeatures",
    "FunctionDenoiser",
    "GaussianDenoiser",
    "InpaintConfig",
    "PatchDiscriminator",
    "PatchGANConfig",
    "SD2Denoiser",
    "SampleResult",
    "SamplerConfig",
    "ScenePrior",
    "ScenePriorConfig",
    "ScheduleConfig",
    "alphas_cumprod",
    "available_models",
    "check_sd2_folder",
    "crop_patches",
    "d_loss",
    "ddim_timesteps",
    "g_loss",
    "inpaint_image",
    "joint_bilateral_upsample",
    "load_dino",
    "make_feature_extractor",
    "missing_sd2_files",
    "opencv_inpaint",
    "resolve_sd2_path",
    "sample_patch_corners",
    "split_prediction",
    "train_scene_prior",
]
