"""CLG's no-worse guard (CoIn paper 4.3 says nothing of it): a stage that rewrites
images must not hand on something worse than it received. Without ground truth, "worse" is measured
three ways: the consistency residual to the reference (by both geometric routes), the texture
inside the mask, and the colour distance of the mask to its surroundings. `pick` chooses among a
view's candidate outputs (with and without the colour match of `coin_cl.pipeline.clg_detail`) the
one that passes with the lowest residual, or keeps the input."""

from __future__ import annotations

from typing import Any

import numpy as np

from coin_cl.pipeline.clg_config import CLGConfig


def colour_distance(img: np.ndarray, mask: np.ndarray, ring_px: int = 8) -> float:
    """Distance between the colour statistics (Lab mean and standard deviation per channel) inside
    `mask` (H, W) bool of `img` (H, W, 3) and in a ring of `ring_px` around it: a fill of hues its
    surroundings do not have scores high. NaN without a ring."""
    import cv2

    m = np.asarray(mask, bool)
    ring = cv2.dilate(m.astype(np.uint8), np.ones((2 * ring_px + 1,) * 2, np.uint8)).astype(bool) & ~m
    if not m.any() or not ring.any():
        return float("nan")
    lab = cv2.cvtColor(np.clip(img, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)
    a, b = lab[m], lab[ring]
    return float(np.abs(a.mean(0) - b.mean(0)).sum() + np.abs(a.std(0) - b.std(0)).sum())


def _finite(x: float | None) -> bool:
    return x is not None and bool(np.isfinite(x))


def _rose(before: float | None, after: float | None) -> bool:
    return _finite(before) and _finite(after) and after > before


def no_worse(
    inp: np.ndarray, out: np.ndarray, mask: np.ndarray, rec: dict[str, Any], cfg: CLGConfig
) -> list[str]:
    """Why `out` is worse than the input `inp` of a view (empty: it is not), on the measures CLG can
    compute without ground truth: the consistency residual to the reference (from `rec`), the
    texture inside the mask (`metrics.mask_texture`) and the colour distance to the surroundings.
    Writes the texture and colour figures into `rec`."""
    from coin_cl.metrics import mask_texture

    why = []
    rb, ra = rec.get("residual_before"), rec.get("residual_after")
    if _rose(rb, ra):
        why.append(f"residual to the reference {rb:.4f} -> {ra:.4f}")
    # the same residual by the other geometric route (view n's depth lifted into the reference): the
    # warp through P_k alone can favour detail that only P_k's own geometry aligns
    lb, la = rec.get("lifted_before"), rec.get("lifted_after")
    if _rose(lb, la):
        why.append(f"residual to the reference lifted with the view's depth {lb:.4f} -> {la:.4f}")
    t_in, t_out = mask_texture(inp, mask), mask_texture(out, mask)
    rec["texture_input"], rec["texture_output"] = t_in, t_out
    if t_out < (1.0 - cfg.texture_tol) * t_in:
        why.append(f"texture {t_in:.4f} -> {t_out:.4f}")
    c_in, c_out = colour_distance(inp, mask), colour_distance(out, mask)
    rec["colour_input"], rec["colour_output"] = c_in, c_out
    if np.isfinite(c_in) and np.isfinite(c_out) and c_out > (1.0 + cfg.colour_tol) * c_in + 1.0:
        why.append(f"colour distance to the surroundings {c_in:.1f} -> {c_out:.1f}")
    return why


def pick(
    inp: np.ndarray, candidates: list[tuple[np.ndarray, dict[str, Any]]], mask: np.ndarray, cfg: CLGConfig
) -> tuple[np.ndarray, dict[str, Any]]:
    """(output, record) for a view: of its candidate (output [H, W, 3], record) pairs, the one that
    is not worse than `inp` (`no_worse`) with the lowest residual to the reference (an unmeasured one
    ranks last; ties keep the earlier candidate); when none is,
    `inp` with the first candidate's record marked "kept input" and its reasons. With several
    candidates the record lists each one's residual and reasons under "candidates"."""
    verdicts = [no_worse(inp, out, mask, rec, cfg) for out, rec in candidates]
    ok = [i for i, why in enumerate(verdicts) if not why]
    if ok:
        # a residual that could not be measured (no support) ranks after every measured one
        res = [candidates[i][1].get("residual_after") for i in ok]
        best = ok[min(range(len(ok)), key=lambda j: res[j] if _finite(res[j]) else np.inf)]
        out, rec = candidates[best]
    else:
        out, rec = inp, candidates[0][1]
        rec.update(status="kept input", kept_because=verdicts[0], residual_written=rec.get("residual_before"))
    if len(candidates) > 1:
        rec["candidates"] = [
            {
                "status": r.get("status"),
                "colour_match": r.get("colour_match"),
                "residual_after": r.get("residual_after"),
                "worse": why,
            }
            for (_, r), why in zip(candidates, verdicts)
        ]
    return out, rec
