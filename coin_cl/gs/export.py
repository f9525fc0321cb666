"""Gaussian files other tools open: the 3DGS PLY (SH padded to degree 3), antimatter15's `.splat`,
and a folder laid out as graphdeco's gaussian-splatting writes its output, plus `export_run`, which
turns a `coin-cl run` folder (or a 3DGS PLY) into any of them. docs/EXPORT.md has the user's side.

Formats (`EXPORT_FORMATS`):
- "ply": `Splats.to_ply`: x y z nx ny nz f_dc_0..2 f_rest_0..3K-1 opacity scale_0..2 rot_0..3, all
  float32 little-endian, the same order as graphdeco's `construct_list_of_attributes` and gsplat's
  PLY exporter; K = 15 (degree 3) by default, which SIBR's fixed 62-float record needs.
- "splat": antimatter15's viewer format, no header, 32 bytes a Gaussian: position 3 x f32, scale
  3 x f32 (exp of the log scales), colour RGBA 4 x u8 (SH degree 0 -> [0, 255], alpha = sigmoid of
  the opacity logit), rotation 4 x u8 (unit quaternion wxyz, each q * 128 + 128 clipped to 0..255).
  Rows sorted by exp(sum of log scales) * sigmoid(opacity), largest first, as its converter does
  (its viewer draws what comes first when it runs out of budget). View-dependent colour is lost.
- "graphdeco": `point_cloud/iteration_N/point_cloud.ply` (degree 3), `cameras.json` (graphdeco's
  `camera_to_JSON`: id, img_name (the stem), width, height, position (camera centre), rotation
  (camera-to-world 3x3, OpenCV axes, row-major), fx, fy), `cfg_args` (the `Namespace(...)` line
  graphdeco's train.py writes; `source_path`: the scene the run was made from, when it still exists).

Gaussians holding NaN/Inf are left out of every format, with the count logged.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from coin_cl.atomic import atomic_write, write_text
from coin_cl.gs.sh import C0, MAX_SH_DEGREE
from coin_cl.gs.splats import Splats

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("ply", "graphdeco", "splat")
# antimatter15's record: 3 f32 position, 3 f32 scale, 4 u8 RGBA, 4 u8 quaternion (w x y z).
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
SPLAT_RECORD_BYTES = 32
# graphdeco's default number of training steps: tools that look for "the last iteration" find it.
GRAPHDECO_ITERATION = 30_000
# Where a `coin-cl run` folder keeps its final Gaussians and its scene.
RUN_PLY = Path("eval") / "point_cloud.ply"
RUN_SCENE = Path("0_scene") / "scene"


# ---------------------------------------------------------------------------------------------- .splat


def splat_records(splats: Splats) -> np.ndarray:
    """Splats (N finite Gaussians) -> (N,) `SPLAT_DTYPE` records in antimatter15's order (module doc)."""
    means = splats.means.detach().cpu().double().numpy()
    log_s = splats.log_scales.detach().cpu().double().numpy()
    logit = splats.opacity_logits.detach().cpu().double().numpy()
    dc = splats.sh_dc.detach().cpu().double().numpy()
    q = splats.quats.detach().cpu().double().numpy()
    alpha = 1.0 / (1.0 + np.exp(-logit))
    order = np.argsort(-np.exp(log_s.sum(1)) * alpha, kind="stable")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    rec = np.empty(len(means), SPLAT_DTYPE)
    rec["position"] = means
    rec["scale"] = np.exp(log_s)
    rgb = 0.5 + C0 * dc
    rec["rgba"] = np.clip(np.round(np.concatenate([rgb, alpha[:, None]], 1) * 255), 0, 255).astype(np.uint8)
    rec["rot"] = np.clip(np.round(q * 128 + 128), 0, 255).astype(np.uint8)
    return rec[order]


def write_splat(splats: Splats, path: str | Path) -> int:
    """Write `.splat` (module doc) atomically; returns how many Gaussians holding NaN/Inf were left out."""
    g, dropped = splats.finite_for(path)
    rec = splat_records(g)
    atomic_write(path, lambda p: p.write_bytes(rec.tobytes()))
    return dropped


def read_splat(path: str | Path) -> dict[str, np.ndarray]:
    """A `.splat` file -> {"means" (N, 3), "scales" (N, 3), "rgba" (N, 4) in [0, 1], "quats" (N, 4)
    wxyz in [-1, 1]} float32. A size that is not a multiple of 32 bytes is a ValueError naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f".splat file {path} not found")
    data = path.read_bytes()
    if len(data) % SPLAT_RECORD_BYTES:
        raise ValueError(
            f"{path} is {len(data)} bytes, not a whole number of {SPLAT_RECORD_BYTES}-byte .splat records "
            "(truncated?); re-export it"
        )
    rec = np.frombuffer(data, SPLAT_DTYPE)
    return {
        "means": rec["position"].astype(np.float32),
        "scales": rec["scale"].astype(np.float32),
        "rgba": rec["rgba"].astype(np.float32) / 255.0,
        "quats": (rec["rot"].astype(np.float32) - 128.0) / 128.0,
    }


# ---------------------------------------------------------------------------------------------- graphdeco


def graphdeco_camera(i: int, cam) -> dict:
    """One entry of graphdeco's cameras.json for a `coin_cl.scene.Camera` (OpenCV axes, as graphdeco)."""
    c2w = cam.camtoworld
    return {
        "id": i,
        "img_name": Path(cam.name).stem or f"{i:05d}",
        "width": int(cam.width),
        "height": int(cam.height),
        "position": c2w[:3, 3].tolist(),
        "rotation": [row.tolist() for row in c2w[:3, :3]],
        "fy": float(cam.K[1, 1]),
        "fx": float(cam.K[0, 0]),
    }


def cfg_args_line(
    source_path: str | Path | None, model_path: str | Path, sh_degree: int = MAX_SH_DEGREE
) -> str:
    """graphdeco's cfg_args: the repr of its argparse Namespace (SIBR parses it by key)."""
    src = str(Path(source_path).resolve()) if source_path is not None else ""
    model = str(Path(model_path).resolve())
    return (
        f"Namespace(sh_degree={sh_degree}, source_path={src!r}, model_path={model!r}, "
        "images='images', resolution=-1, white_background=False, data_device='cuda', eval=False)"
    )


def write_graphdeco(
    splats: Splats,
    out: str | Path,
    cameras: list | None = None,
    *,
    iteration: int = GRAPHDECO_ITERATION,
    source_path: str | Path | None = None,
) -> int:
    """A graphdeco-style output folder `out` (module doc); `cameras`: `coin_cl.scene.Camera`s for
    cameras.json (None: an empty list). Returns how many Gaussians holding NaN/Inf were left out."""
    out = Path(out)
    dropped = splats.to_ply(
        out / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply", MAX_SH_DEGREE
    )
    doc = [graphdeco_camera(i, c) for i, c in enumerate(cameras or [])]
    write_text(out / "cameras.json", json.dumps(doc))
    write_text(out / "cfg_args", cfg_args_line(source_path, out))
    return dropped


# ---------------------------------------------------------------------------------------------- runs


def _captured_scene(run: Path) -> Path | None:
    """The scene folder the run was made from (run.json's scene path) when it still exists: the
    `source_path` graphdeco's tools reopen (SIBR reads its COLMAP model), else None."""
    try:
        path = json.loads((run / "run.json").read_text())["scene"]["path"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return Path(path) if isinstance(path, str) and Path(path).is_dir() else None


def export_splats(
    splats: Splats,
    fmt: str,
    out: str | Path,
    *,
    cameras: list | None = None,
    sh_degree: int = MAX_SH_DEGREE,
    iteration: int = GRAPHDECO_ITERATION,
    source_path: str | Path | None = None,
) -> int:
    """Write `splats` as `fmt` ("ply", "splat", "graphdeco") to `out` (a file; a folder for
    graphdeco); returns how many Gaussians holding NaN/Inf were left out."""
    if fmt == "ply":
        return splats.to_ply(out, sh_degree)
    if fmt == "splat":
        return write_splat(splats, out)
    if fmt == "graphdeco":
        return write_graphdeco(splats, out, cameras, iteration=iteration, source_path=source_path)
    raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(EXPORT_FORMATS)}")


def export_run(
    source: str | Path,
    fmt: str,
    out: str | Path,
    *,
    sh_degree: int = MAX_SH_DEGREE,
    iteration: int = GRAPHDECO_ITERATION,
) -> tuple[Path, int, int]:
    """Export the final Gaussians of a `coin-cl run` folder (its eval/point_cloud.ply, cameras from
    its 0_scene/scene) or of a 3DGS PLY file `source` as `fmt` to `out`. Returns (out, Gaussians
    written, Gaussians left out for NaN/Inf). graphdeco's cameras.json needs a run folder; from a
    bare PLY it is an empty list."""
    source, out = Path(source), Path(out)
    cameras, scene_dir = None, None
    if source.is_dir():
        ply = source / RUN_PLY
        if not ply.is_file():
            raise FileNotFoundError(
                f"{source} has no {RUN_PLY}: give a coin-cl run folder whose eval stage has run "
                "(or a 3DGS PLY)"
            )
        scene_dir = source / RUN_SCENE
        if fmt == "graphdeco" and scene_dir.is_dir():
            from coin_cl.scene import load_scene

            cameras = load_scene(scene_dir, priors=False).cameras
            scene_dir = _captured_scene(source) or scene_dir
    elif source.is_file():
        ply = source
    else:
        raise FileNotFoundError(f"{source} not found: give a coin-cl run folder or a 3DGS PLY file")
    if out.resolve() == ply.resolve():
        raise ValueError(f"--out {out} is the file being exported; choose another path")
    splats = Splats.from_ply(ply)
    dropped = export_splats(splats, fmt, out, cameras=cameras, sh_degree=sh_degree, iteration=iteration,
                            source_path=scene_dir)  # fmt: skip
    return out, len(splats) - dropped, dropped


__all__ = [
    "EXPORT_FORMATS",
    "SPLAT_DTYPE",
    "SPLAT_RECORD_BYTES",
    "export_run",
    "export_splats",
    "graphdeco_camera",
    "read_splat",
    "splat_records",
    "write_graphdeco",
    "write_splat",
]
