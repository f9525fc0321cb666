"""Benchmark of the removal geometry: the background depth term and carving, with the ghost figure.

Rows share stages 0 and 1 and train Ref-GS only (no CLG, no TE-D, input masks), so they differ only by
the geometry switches: `no_bg_depth` (RefGSConfig(bg_depth=False), no carve: neither geometry term),
`bg_depth` (the default: every view's mask held to its background depth D_bg), `carve` (the default plus
`CoInConfig.carve`), `bg_depth_fill` (D_bg by the 2D fill alone, RefGSConfig(bg_depth_planes=False)).
First a table of D_bg itself against the reference depth in the test views' masks, with and without the
planar continuation (`coin_cl.gs.surface_planes`): the share more than 10 % in front (D_bg's own ghost
figure: what the term lets stand), more than 10 % behind (where its front side pushes the true surface
back), the median relative error and the seconds per view (`--dbg-only`: that table alone).
Ghost figure (`benchmarks/ghost.py`): the share of mask pixels of the object-absent
test views rendered more than 10 % in front of the reference depth (exact on the synthetic room; on
SPIn-NeRF a Scaffold-GS fitted to the 5 object-absent views). Also the visibility estimate.

    python benchmarks/carve.py --scene spinnerf [--iters 400] [--out DIR]
    python benchmarks/carve.py --scene room [--iters 300]
    python benchmarks/carve.py --scene room --dbg-only

Last line JSON: {row: {ghost, m_psnr, hf_ratio, bbox_gmsd, minutes}, observed_share, dbg_ghost, ...}.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, default_data, git_commit  # noqa: E402
from ghost import ghost_of_run, reference_depths  # noqa: E402

from coin_cl.gs.background_depth import background_depth, background_point_flags  # noqa: E402
from coin_cl.gs.carve import build_carve, observed_share  # noqa: E402
from coin_cl.gs.refgs import RefGSConfig  # noqa: E402
from coin_cl.pipeline.coin import CoInConfig, inpaint  # noqa: E402
from coin_cl.pipeline.runner import share_stages  # noqa: E402
from coin_cl.scene import load_scene, write_synthetic  # noqa: E402
from coin_cl.scene.synthetic import make_synthetic  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scene", choices=("spinnerf", "room"), default="spinnerf")
    ap.add_argument("--iters", type=int, default=None, help="Ref-GS steps (default 400 / 300)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--dbg-only", action="store_true", help="only D_bg's error (planes off / on), no training"
    )
    args = ap.parse_args()
    out = args.out or Path(__file__).resolve().parent / "out" / f"carve_{args.scene}"
    if args.scene == "spinnerf":
        data, res_scale, iters, syn = default_data(), 0.5, args.iters or 400, None
        scene = load_scene(data, resolution=res_scale)
        depths = reference_depths(
            scene, Path(__file__).resolve().parent / "out" / "ghost_reference" / "r0.5_i600"
        )
    else:
        syn = make_synthetic(coverage=90, n_views=24, width=128, height=96, seed=0)
        data, res_scale, iters = write_synthetic(out / "room", syn), 1.0, args.iters or 300
        scene = load_scene(data)
        depths = {i: syn.depth_absent[i].astype(np.float64) for i in scene.test_idx}
    train = list(scene.train_idx)
    vol = build_carve(
        [scene.cameras[i] for i in train], [scene.masks[i] for i in train], np.asarray(scene.points)
    )
    share = observed_share(vol)[0]
    dbg = {planes: _dbg_error(scene, train, depths, planes) for planes in (False, True)}
    dbg_ghost = dbg[True]["front"]
    print(f"\nD_bg against the reference depth in the test views' masks ({args.scene}); CPU {cpu_model()}; "
          f"commit {git_commit()}")  # fmt: skip
    print("| D_bg | > 10 % in front (its ghost) | > 10 % behind | median abs. rel. error | s / view |")
    print("|---|---|---|---|---|")
    for planes, r in dbg.items():
        name = "2D fill + planes (default)" if planes else "2D fill"
        print(f"| {name} | {r['front']:.3f} | {r['behind']:.3f} | {r['median']:.3f} | {r['seconds']:.2f} |")
    if args.dbg_only:
        print(
            json.dumps(
                {"dbg": {str(k): v for k, v in dbg.items()}, "commit": git_commit(), "cpu": cpu_model()}
            )
        )
        return 0
    base = CoInConfig(resolution=res_scale, iters_refgs=iters, iters_ted_finetune=0, iters_ted_adversarial=0,
                      prior_seconds=120, skip=("clg",), inpaint_region="input")  # fmt: skip
    rows = {}
    variants = (("bg_depth", base), ("no_bg_depth", replace(base, refgs=RefGSConfig(bg_depth=False))),
                ("bg_depth_fill", replace(base, refgs=RefGSConfig(bg_depth_planes=False))),
                ("carve", replace(base, carve=True)))  # fmt: skip
    for name, cfg in variants:
        if name != variants[0][0]:
            share_stages(out / variants[0][0], out / name, ("0_scene", "1_inpaint"))
        t = time.perf_counter()
        res = inpaint(data, out / name, config=cfg)
        rows[name] = {k: res.metrics[k] for k in ("m_psnr", "hf_ratio", "bbox_gmsd")}
        rows[name]["minutes"] = (time.perf_counter() - t) / 60
        rows[name]["ghost"] = ghost_of_run(out / name, scene, depths)["ghost"]
    print(f"\nremoval geometry on {args.scene} ({iters} Ref-GS steps, no CLG/TE-D); CPU {cpu_model()}; "
          f"commit {git_commit()}; visibility estimate {share:.3f}; "
          f"ghost of D_bg itself {dbg_ghost:.3f}")  # fmt: skip
    print("| row | ghost | m-PSNR | HF ratio | bbox GMSD | minutes |\n|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {r['ghost']:.3f} | {r['m_psnr']:.2f} | {r['hf_ratio']:.3f} | {r['bbox_gmsd']:.3f} "
              f"| {r['minutes']:.1f} |")  # fmt: skip
    print(json.dumps({**rows, "observed_share": share, "dbg_ghost": dbg_ghost,
                      "dbg": {str(k): v for k, v in dbg.items()}, "commit": git_commit(),
                      "cpu": cpu_model()}))  # fmt: skip
    return 0


def _dbg_error(scene, train: list[int], depths: dict[int, np.ndarray], planes: bool) -> dict:
    """D_bg (background points flagged by the training views) against the reference depth in the test
    views' masks: the share more than 10 % in front (its ghost figure: what the term lets stand), more
    than 10 % behind (where it pushes the true surface back), the median relative error, and the
    seconds per view."""
    pts = np.asarray(scene.points, np.float64)
    flags = background_point_flags([scene.cameras[i] for i in train], [scene.masks[i] for i in train], pts)
    front = behind = n = 0
    errs, secs = [], []
    for i, ref in depths.items():
        m = np.asarray(scene.masks[i], bool)
        if not m.any():
            continue
        t = time.perf_counter()
        d = background_depth(scene.cameras[i], m, pts[flags], None, 3, object_free=True, planes=planes)
        secs.append(time.perf_counter() - t)
        ok = m & np.isfinite(ref) & (ref > 0)
        r = d[ok] / ref[ok]
        front, behind, n = front + (r < 0.9).sum(), behind + (r > 1.1).sum(), n + ok.sum()
        errs.append(np.abs(r - 1))
    return {"front": float(front / max(n, 1)), "behind": float(behind / max(n, 1)),
            "median": float(np.median(np.concatenate(errs))), "seconds": float(np.mean(secs))}  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
