"""Memory known in advance: the peak memory of a CoIn run (paper 4.2-4.4: the GS stages dominate),
estimated from the image size, the view count and the point count before any stage starts, and
checked against what the machine has. A scene that cannot fit is refused with the estimate and the
setting that makes it fit (`--resolution`, fewer views), instead of being killed by the kernel's
out-of-memory handler an hour in.

The estimate is a sum of parts, each a count times a per-item size:

- `base`: the Python process with torch, the OpenCL runtime, the diffusion nets and the features
  (torch alone is 0.24 GiB resident on this machine kind);
- `images`: every view's pixels, held as float32 RGB in several copies across the stages (the
  captures, the initial inpaints I^_n, the composited targets, the CLG images I~_n, TE-D's real
  images, the trainer's tensors) plus masks: `BYTES_PER_VIEW_PIXEL` per pixel of every view;
- `model`: Scaffold-GS anchors (one per occupied voxel of the SfM points, at most one per point;
  growth during training allowed for by `ANCHOR_GROWTH`) with their 10 offsets, features,
  gradients, Adam moments and the decoded Gaussians of a render with their saved activations;
- `render`: one view's render buffers and tile lists, per pixel of a view.

Calibration: a plain Scaffold-GS training on SPIn-NeRF's 34 training views at 504x284 (95k
anchors from 73k points) peaked at 1.10 GiB resident (docs/RESULTS.md); with the trainer's one
image copy (24 B per pixel) and those 95k anchors these constants give it 1.08 GiB. The pipeline's
estimate adds the stages' other image copies and anchor growth, then a 25 % margin: 1.9 GiB for
that scene. `benchmarks/faults.py` prints the estimate beside the measured peak of its runs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

GIB = 1024**3
BASE_BYTES = int(0.45 * GIB)
BYTES_PER_VIEW_PIXEL = 64  # ~5 float32 RGB copies of every view + masks
BYTES_PER_ANCHOR = 5 * 1024  # parameters x 4 (value, grad, Adam m, v) + a render's decoded offsets
ANCHOR_GROWTH = 2.0  # anchor growing may add up to this factor over the SfM points
BYTES_PER_RENDER_PIXEL = 512  # image, depth, alpha and their gradients + tile lists of one view
SAFETY = 1.25  # what the estimate is multiplied by before it is compared
RESOLUTIONS = (0.75, 0.5, 0.375, 0.25, 0.125)  # the scales suggested when a scene does not fit
# Decoding a view at its file's size holds float32 RGB (12 B/px) and a bool mask (1 B/px) for the
# whole scene, plus the file's 8-bit pixels and the float copy of the view being converted.
DECODE_BYTES_PER_PIXEL = 13
DECODE_TRANSIENT_BYTES_PER_PIXEL = 4 + 12
ENV_LIMIT = "COIN_MEMORY_LIMIT_GB"  # pretend the machine has this much (tests, shared machines)


class SceneTooLargeError(ValueError):
    """The scene's estimated peak memory exceeds what the machine has."""


@dataclass
class MemoryEstimate:
    """bytes: the estimated peak (safety factor included); parts: its terms (before the factor);
    available: what the machine has (None: unknown)."""

    bytes: int
    parts: dict[str, int]
    available: int | None

    @property
    def fits(self) -> bool:
        return self.available is None or self.bytes <= self.available


def estimate_peak_bytes(width: int, height: int, n_views: int, n_points: int) -> tuple[int, dict[str, int]]:
    """(estimated peak bytes with the safety factor, {part: bytes}) of a CoIn run on `n_views`
    views of `width` x `height` pixels seeded with `n_points` SfM points."""
    px = int(width) * int(height)
    parts = {
        "base": BASE_BYTES,
        "images": BYTES_PER_VIEW_PIXEL * px * int(n_views),
        "model": int(BYTES_PER_ANCHOR * ANCHOR_GROWTH * max(int(n_points), 1)),
        "render": BYTES_PER_RENDER_PIXEL * px,
    }
    return int(SAFETY * sum(parts.values())), parts


def available_bytes() -> int | None:
    """Memory this process may still use: MemAvailable of /proc/meminfo, capped by the cgroup's
    limit (containers) and by $COIN_MEMORY_LIMIT_GB; None where none of these can be read."""
    cands = []
    env = os.environ.get(ENV_LIMIT)
    if env:
        cands.append(int(float(env) * GIB))
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                cands.append(int(line.split()[1]) * 1024)
    except OSError:
        try:  # other Unixes: free pages (an under-estimate of what can be had; safe)
            cands.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            pass
    for limit, used in (("memory.max", "memory.current"), ("memory/memory.limit_in_bytes", None)):
        try:
            lim = Path("/sys/fs/cgroup", limit).read_text().strip()
            if lim != "max" and int(lim) < 1 << 60:
                cur = int(Path("/sys/fs/cgroup", used).read_text()) if used else 0
                cands.append(int(lim) - cur)
                break
        except (OSError, ValueError):
            continue
    return min(cands) if cands else None


def fit_hint(w: int, h: int, n: int, pts: int, have: int) -> str:
    """What makes a run of `n` views of `w` x `h` with `pts` points fit in `have` bytes: the
    largest `--resolution` of RESOLUTIONS that fits, else the view count to aim at, else a machine
    with more memory."""
    hint = None
    for r in RESOLUTIONS:
        if estimate_peak_bytes(round(w * r), round(h * r), n, pts)[0] <= have:
            got = estimate_peak_bytes(round(w * r), round(h * r), n, pts)[0]
            hint = f"--resolution {r} (about {got / GIB:.1f} GiB)"
            break
    if hint is None:
        per_view = SAFETY * (BYTES_PER_VIEW_PIXEL * w * h * min(RESOLUTIONS) ** 2)
        fixed = estimate_peak_bytes(round(w * min(RESOLUTIONS)), round(h * min(RESOLUTIONS)), 0, pts)[0]
        views = int(max(0, have - fixed) // max(per_view, 1))
        hint = (
            f"fewer views (about {views} at --resolution {min(RESOLUTIONS)})"
            if views >= 2
            else f"a machine with more memory (2 views at --resolution {min(RESOLUTIONS)} do not fit; "
            "a thinner SfM point cloud helps when the model part is large)"
        )
    return hint


def check_memory(scene, n_points: int | None = None) -> MemoryEstimate:
    """Estimate `scene`'s peak memory (at its current resolution) and refuse it when it cannot fit.

    Raises `SceneTooLargeError` (a ValueError: one line in the CLI) with the estimate, what is
    available and the largest `--resolution` that fits (or, when none does, the view count to
    aim at). Returns the estimate otherwise.
    """
    cam = scene.cameras[0]
    w, h, n = cam.width, cam.height, len(scene)
    pts = len(scene.points) if n_points is None else n_points
    need, parts = estimate_peak_bytes(w, h, n, pts)
    have = available_bytes()
    est = MemoryEstimate(need, parts, have)
    if est.fits:
        return est
    hint = fit_hint(w, h, n, pts, have)
    parts_txt = ", ".join(f"{k} {v / GIB:.2f}" for k, v in parts.items())
    raise SceneTooLargeError(
        f"scene {scene.path}: {n} views of {w}x{h} with {pts} points need about {need / GIB:.1f} GiB "
        f"(estimate: {parts_txt} GiB, x{SAFETY} margin) but {have / GIB:.1f} GiB are available: use {hint}"
    )


def check_scene_files(path, resolution: float | None) -> MemoryEstimate:
    """The memory check made before a scene folder is decoded: from the image headers alone
    (`coin_cl.scene.image_sizes`; a header declaring more than `scene.io.MAX_IMAGE_PIXELS` is
    refused there, naming the file) the peak of decoding every view at its file's size
    (DECODE_BYTES_PER_PIXEL per pixel of all views plus one view's transient copies) and the run's
    estimate at the working size `resolution` (None: `budget.working_resolution`) without the
    points (not known before loading; `check_memory` adds them once loaded). Refuses either with
    `SceneTooLargeError`, one line naming the folder and what to do; returns the larger estimate.
    """
    from coin_cl.pipeline.budget import working_resolution
    from coin_cl.scene import image_sizes

    sizes = image_sizes(path)
    if not sizes:
        raise FileNotFoundError(f"no .png/.jpg images in scene {path}")
    px = [w * h for _, w, h in sizes]
    decode = BASE_BYTES + DECODE_BYTES_PER_PIXEL * sum(px) + DECODE_TRANSIENT_BYTES_PER_PIXEL * max(px)
    decode = int(SAFETY * decode)
    _, w, h = max(sizes, key=lambda s: s[1] * s[2])
    r = resolution if resolution is not None else working_resolution(w, h)
    run, parts = estimate_peak_bytes(round(w * r), round(h * r), len(sizes), 0)
    have = available_bytes()
    est = MemoryEstimate(max(decode, run), {**parts, "decode": decode}, have)
    if have is not None and run > have:
        ww, hh = round(w * r), round(h * r)
        raise SceneTooLargeError(
            f"scene {path}: {len(sizes)} views of {ww}x{hh} need about {run / GIB:.1f} GiB before counting "
            f"the points, but {have / GIB:.1f} GiB are available: use {fit_hint(ww, hh, len(sizes), 0, have)}"
        )
    if have is not None and decode > have:
        raise SceneTooLargeError(
            f"scene {path}: decoding its {len(sizes)} images ({sum(px) / 1e6:.0f} megapixels, the largest "
            f"{w}x{h}) needs about {decode / GIB:.1f} GiB before they are scaled down, but {have / GIB:.1f} "
            "GiB are available: downscale the photos first (e.g. `coin-cl prepare --width 1008`) or use "
            "fewer of them"
        )
    return est
