"""CLG for one view (CoIn paper 4.3): guided DDIM sampling on the crop around its mask, pasted back
inside the mask, or without a sampler the reference warped through P_k (`warp_fill`); each with its
record (energies, consistency residuals before and after, support). `coin_cl.pipeline.clg` runs it
over the views; the energy is `coin_cl.pipeline.clg_energy`."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from coin_cl.diffusion.inpaint2d import paste
from coin_cl.diffusion.sampling import DDIMSampler, Denoiser
from coin_cl.metrics import mask_texture
from coin_cl.pipeline.clg_config import CLGConfig
from coin_cl.pipeline.clg_detail import (
    ReferenceView,
    colour_target,
    crop_bands,
    high_band,
    reference_detail,
    reference_warp,
    texture_gain,
)
from coin_cl.pipeline.clg_energy import make_energy, setup_view, work_size
from coin_cl.pipeline.reprojection import masked_residual, residual_to_reference, warp_fill
from coin_cl.scene.io import to_uint8

if TYPE_CHECKING:
    from coin_cl.engine import DeviceLike
    from coin_cl.scene import Camera


def written(out: np.ndarray) -> np.ndarray:
    """What the PNG will hold (uint8) as float: the residuals are of the written image."""
    return to_uint8(out).astype(np.float32) / 255


def lifted_residual(img: np.ndarray, cam: Camera, mask: np.ndarray, depth_n: np.ndarray | None,
                    ref: ReferenceView) -> float:  # fmt: skip
    """The residual to the reference by the other geometric route (`residual_to_reference`): view n's
    mask pixels of `img` lifted with its own depth and projected into the reference's mask; nan
    without a depth or a reference mask."""
    if depth_n is None or ref.mask is None:
        return float("nan")
    region = np.asarray(mask, bool) & np.isfinite(depth_n)
    return residual_to_reference([cam, ref.cam], [depth_n, None], [img, None], [region, None], 1,
                                 ref.image, ref.mask)  # fmt: skip


def input_residuals(inp_n: np.ndarray, cam: Camera, mask: np.ndarray, depth_n: np.ndarray | None,
                    ref: ReferenceView, warp: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:  # fmt: skip
    """The input's residuals by both routes and the support (once per view, shared by its candidates)."""
    r_before, n_sup = masked_residual(inp_n, *warp, mask)
    return {"residual_before": r_before, "support_px": n_sup,
            "lifted_before": lifted_residual(inp_n, cam, mask, depth_n, ref)}  # fmt: skip


def output_residuals(out: np.ndarray, cam: Camera, mask: np.ndarray, depth_n: np.ndarray | None,
                     ref: ReferenceView, warp: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:  # fmt: skip
    """A candidate's residuals by both routes, of what its PNG will hold."""
    w = written(out)
    return {"residual_after": masked_residual(w, *warp, mask)[0],
            "lifted_after": lifted_residual(w, cam, mask, depth_n, ref)}  # fmt: skip


def warp_view(n: int, cam: Camera, inp_n: np.ndarray, ren_n: np.ndarray, depth_n: np.ndarray | None,
              mask: np.ndarray, ref: ReferenceView, device: DeviceLike, harmonise: bool = False,
              detail_gain_max: float = 1.0) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """CLG without a sampler for view n: (output [H, W, 3], record). The fill is the reference itself
    (both bands: no band split is needed, the detail comes through the same warp as the colours),
    with R_n `ren_n` where the warp does not land; `harmonise`: blended in the gradient domain
    against view n's surroundings (`propagated`, with `ren_n` as the view's own fill), its detail
    band gained back towards the input's texture by at most `detail_gain_max` (`texture_gain`)."""
    warp = reference_warp(ref, cam, device)
    gain = 1.0
    if harmonise:
        m = np.asarray(mask, bool)
        out, n_sup = propagated(np.where(m[..., None], ren_n, inp_n), mask, warp)
        # the warp's resampling softens the reference's detail: its band above half the view's size
        # is gained back towards the input's texture, as the sampler's detail band is (at most
        # detail_gain_max)
        H, W = m.shape
        high = high_band(out, W // 2, H // 2)

        def compose(g: float) -> np.ndarray:
            return np.where(m[..., None], np.clip(out + (g - 1.0) * high, 0, 1), inp_n).astype(np.float32)

        out, gain = texture_gain(compose, lambda o: mask_texture(written(o), m), mask_texture(inp_n, m),
                                 detail_gain_max)  # fmt: skip
    else:
        out, n_sup = warp_fill(inp_n, ren_n, mask, *warp)
    rec = {"view": n, "status": "propagated" if harmonise else "warped", "detail_gain": gain,
           **input_residuals(inp_n, cam, mask, depth_n, ref, warp),
           **output_residuals(out, cam, mask, depth_n, ref, warp), "support_px": n_sup,
           "hole_px": int(mask.sum())}  # fmt: skip
    return out, rec


def propagated(
    inp_n: np.ndarray, mask: np.ndarray, warp: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, int]:
    """The reference's answer in view n: inside `mask` (H, W) bool the reference warped through P_k
    (`reference_warp`'s colours and weights) where the warp lands, I^_n `inp_n` (H, W, 3) elsewhere,
    blended in the gradient domain against I^_n's pixels outside the mask (`poisson_blend`, a
    gradient between the warped part and anything else not carried): the reference's texture on
    colours that meet view n's own surroundings, which differ from the reference's in light and
    exposure. Returns ((H, W, 3) float32, supported pixels); outside the mask bit-identical to I^_n."""
    from coin_cl.diffusion.poisson import poisson_blend

    warped, weight = warp
    m = np.asarray(mask, bool)
    sup = m & (weight > 0)
    if not sup.any():
        return inp_n.astype(np.float32, copy=True), 0
    guide = np.where(sup[..., None], warped[..., :3], inp_n)
    out = poisson_blend(inp_n, guide, m, sup.astype(np.int8))
    return np.where(m[..., None], out, inp_n).astype(np.float32), int(sup.sum())


def sample_view(n: int, stem: str, cam: Camera, inp_n: np.ndarray, ren_n: np.ndarray,
                depth_n: np.ndarray | None, mask: np.ndarray, ref: ReferenceView, denoiser: Denoiser,
                features: Callable, cfg: CLGConfig,
                device: DeviceLike) -> list[tuple[np.ndarray, dict[str, Any]]]:  # fmt: skip
    """Guided sampling for view n on its crop, pasted back inside the mask: candidate (output
    [H, W, 3], record) pairs, the colour-matched one first (`CLGConfig.colour_match`), then the
    unmatched one; `clg_guard.pick` chooses."""
    from tqdm import tqdm

    work, n_steps = work_size(denoiser), cfg.num_steps(denoiser)
    prob = setup_view(ref.cam, cam, ref.image, inp_n, ren_n, ref.depth, depth_n, mask, ref.points, features,
                      work, cfg, device)  # fmt: skip
    energy = make_energy(prob, features, cfg, device)
    cond = denoiser.make_condition(prob.image, prob.hole, cfg.prompt or "")  # None outside a run: no text
    uncond = None
    if cfg.sampler.cfg_scale != 1.0 and cfg.prompt and hasattr(denoiser, "encode_prompt"):
        uncond = type(cond)(cond.mask, cond.masked_latent, denoiser.encode_prompt("").expand_as(cond.text))
    if hasattr(denoiser, "latent_channels"):  # latent model (SD2): the VAE's grid
        f = int(denoiser.vae_factor)
        shape: tuple[int, ...] = (1, int(denoiser.latent_channels), work // f, work // f)
    else:
        shape = tuple(prob.image.shape)
    g = torch.Generator().manual_seed((0 if cfg.seed is None else cfg.seed) + n)
    sampler = DDIMSampler(denoiser, cfg.sampler_config(denoiser))
    # strength < 1 (SDEdit): start from I^_n's crop noised to that share of the trajectory
    start = min(n_steps - 1, round((1.0 - cfg.strength) * n_steps))
    if start:
        with torch.no_grad():
            z = sampler.noised(denoiser.encode(prob.image).float(), start, g)
    else:
        z = torch.randn(shape, generator=g)
    sbar = tqdm(total=n_steps - start, desc=f"  {stem} steps", leave=False, disable=not cfg.progress)
    res = sampler.sample(
        z, cond, uncond, energy=energy, generator=g, callback=lambda *_, b=sbar: b.update(1), start=start
    )
    sbar.close()
    with torch.no_grad():
        # the last step's clean x0 prediction (as the scene prior's inpaint; for SD2 it equals z at
        # alpha_bar_0 up to sqrt(1 - alpha_bar_0) of predicted noise)
        x = denoiser.decode(res.x0).clamp(0, 1).float()
        e_in, e_out = float(energy(prob.image)), float(energy(x))
    fill = x[0].permute(1, 2, 0).numpy()
    scale = cfg.detail_split * work / prob.side  # view n's split as a share of its full size
    warp = reference_warp(ref, cam, device, scale if cfg.detail == "reference" else None)
    ref_detail = reference_detail(warp) if cfg.detail == "reference" else None
    # with the colour match, the unmatched composite is a candidate too: the match is global over the
    # hole and can move a well-coloured sample away from the reference where the support is partial
    colours = [(colour_target(warp, inp_n), mask), None] if cfg.colour_match else [None]
    common = {
        "view": n, "status": "guided" if cfg.sampler.guidance_scale else "unguided", "steps": n_steps,
        "energy_input": e_in, "energy_output": e_out, "energies": res.energies,
        "support_work_px": int(prob.support.sum()), "hole_work_px": int(prob.hole.sum()),
        "n_points": int(len(ref.points)), "crop": [prob.y0, prob.x0, prob.side], "work": work,
        "detail": cfg.detail, "start_step": start, **input_residuals(inp_n, cam, mask, depth_n, ref, warp),
    }  # fmt: skip
    H, W = mask.shape
    ys = slice(max(prob.y0, 0), min(prob.y0 + prob.side, H))
    xs = slice(max(prob.x0, 0), min(prob.x0 + prob.side, W))
    t_in = mask_texture(inp_n, mask)

    def composite(bands: tuple[np.ndarray, np.ndarray], gain: float) -> np.ndarray:
        back = (bands[0] + gain * bands[1]).astype(np.float32)
        full = inp_n.copy()
        full[ys, xs] = back[ys.start - prob.y0 : ys.stop - prob.y0, xs.start - prob.x0 : xs.stop - prob.x0]
        return paste(inp_n, np.clip(full, 0, 1), mask, cfg.feather_px)

    candidates = []
    for colour in colours:
        # the written image's texture is what the guard and TE-D see
        # the bands once per candidate: the top-up only rescales the high one
        bands = crop_bands(fill, inp_n, prob.y0, prob.x0, prob.side, cfg.detail, ref_detail,
                           cfg.detail_split, colour, cfg.chroma_from_target)  # fmt: skip
        out, gain = texture_gain(
            lambda g, b=bands: composite(b, g),
            lambda o: mask_texture(written(o), mask),
            t_in,
            cfg.detail_gain_max if cfg.detail != "none" else 1.0,
        )
        rec = common | output_residuals(out, cam, mask, depth_n, ref, warp)
        rec |= {
            "colour_match": colour is not None,
            "chroma_from_target": colour is not None and cfg.chroma_from_target,
            "detail_gain": gain,
        }
        candidates.append((out, rec))
    return candidates
