"""Which diffusion model the stages use (CoIn paper 4.1 and 4.3): Stable Diffusion 2 inpainting when
its weights are given (`CoInConfig.sd_path`), else none here, and each stage falls back to the
scene's own prior (`coin_cl.diffusion.scene_prior`, trained by stage 1)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from coin_cl.diffusion.sampling import Denoiser
    from coin_cl.diffusion.sd2 import SD2Denoiser


def sd2_denoiser(sd_path: str | None) -> SD2Denoiser | None:
    """The SD2 inpainting denoiser loaded from `sd_path` (a diffusers folder), None without one."""
    if not sd_path:
        return None
    from coin_cl.diffusion.sd2 import SD2Denoiser

    return SD2Denoiser.from_pretrained(sd_path)


# SD2's CPU-practical mode. Above this estimated wall time for SD2 on every view (stage 1
# unguided + CLG guided, `diffusion.sd2.sd2_run_estimate` from the measured per-step figures), "auto"
# runs SD2 on the reference view only: on 2 cores one unguided step is ~43 s and one guided ~108 s,
# so the shared scene's 34 views would take ~70 h; the reference alone ~0.6 h.
SD2_ALL_VIEWS_MAX_HOURS = 2.0
SD2_MODES = ("auto", "reference_only", "all")


def sd2_on_cpu(sd2: Denoiser) -> bool:
    """Whether the SD2 denoiser's UNet runs on the CPU (True for a denoiser without a UNet)."""
    try:
        return next(sd2.unet.parameters()).device.type == "cpu"
    except (AttributeError, StopIteration):
        return True


def resolve_sd2_mode(
    mode: str, n_views: int, steps: int, on_cpu: bool, clg_steps: int | None = None
) -> tuple[str, str]:
    """The SD2 mode a run uses and why (logged by the caller): "all" = SD2 inpaints every masked view
    (stage 1) and guides every non-reference view (CLG), as the paper; "reference_only" = SD2 inpaints
    the reference view only, the other views take the embedded inpainter in stage 1 and, in CLG, the
    reference warped through P_k where it reaches, their embedded fill elsewhere. "auto" picks
    "reference_only" on a CPU when the estimate for "all" exceeds SD2_ALL_VIEWS_MAX_HOURS.

    n_views: masked views; steps: stage 1's DDIM steps; clg_steps: CLG's (default = steps)."""
    from coin_cl.diffusion.sd2 import sd2_run_estimate

    if mode not in SD2_MODES:
        raise ValueError(f"sd2_mode must be one of {', '.join(SD2_MODES)}, got {mode!r}")
    if mode != "auto":
        return mode, f"SD2 mode {mode} (asked)"
    est = sd2_run_estimate(n_views, steps) if clg_steps is None else _estimate(n_views, steps, clg_steps)
    if est["total_s"] is None:
        return "all", f"SD2 mode all: {est['message']}"
    hours = est["total_s"] / 3600
    if on_cpu and hours > SD2_ALL_VIEWS_MAX_HOURS:
        return "reference_only", (
            f"SD2 mode reference_only (auto): SD2 on every view is estimated at {hours:.1f} h on this CPU, "
            f"above {SD2_ALL_VIEWS_MAX_HOURS:g} h ({est['message']}); SD2 inpaints the reference only, "
            "the other views take the embedded inpainter and the reference warped through P_k in CLG "
            "(sd2_mode='all' / --sd2-mode all for the paper's way)"
        )
    where = "this CPU" if on_cpu else "the accelerator"
    return "all", f"SD2 mode all (auto): estimated {hours:.1f} h on {where} ({est['message']})"


def _estimate(n_views: int, steps: int, clg_steps: int) -> dict:
    """`sd2_run_estimate` with CLG's step count differing from stage 1's."""
    from coin_cl.diffusion.sd2 import sd2_run_estimate

    s1, clg = sd2_run_estimate(n_views, steps), sd2_run_estimate(n_views, clg_steps)
    if s1["total_s"] is None:
        return s1
    total = s1["stage1_s"] + clg["clg_s"]
    return {**s1, "clg_s": clg["clg_s"], "total_s": total,
            "message": f"{s1['message'].split('; total')[0]} (stage 1), CLG {clg_steps} steps ~ "
                       f"{clg['clg_s'] / 3600:.1f} h; total ~ {total / 3600:.1f} h"}  # fmt: skip
