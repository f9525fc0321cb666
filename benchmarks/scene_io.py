"""Scene I/O timings: loading the shared SPIn-NeRF scene and generating the synthetic one.

Usage: python benchmarks/scene_io.py [--data DIR] [--views 40] [--width 256 --height 192]
Prints a table; the LAST line is one JSON object {load_s, synthetic_s, n_views, ...}.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def shared_scene(arg: str | None) -> Path | None:
    cands = [Path(arg)] if arg else []
    if os.environ.get("COIN_DATA"):
        cands.append(Path(os.environ["COIN_DATA"]))
    cands.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    for c in cands:
        if (c / "spinnerf_scene1").is_dir():
            return c / "spinnerf_scene1"
    return None


def supersample_table(syn, width: int, height: int, views: int = 4, ref_ss: int = 6) -> list[dict]:
    """Error against run time of the synthetic ray caster: rays per pixel (supersample^2) against
    a 6x6-supersampled reference of the same views (the anti-aliasing error of the ground truth)."""
    import numpy as np

    from coin_cl.metrics import psnr
    from coin_cl.scene.synthetic import render_view

    cams = syn.cameras[:views]
    ref = [render_view(syn.boxes, c, ref_ss)["absent"] for c in cams]
    print()
    print(
        f"Synthetic ground truth, error against run time ({views} views {width}x{height}, "
        f"reference {ref_ss}x{ref_ss} rays per pixel):"
    )
    print("| rays per pixel | s per view | PSNR vs reference | max abs error |")
    print("|---|---|---|---|")
    out = []
    for ss in (1, 2, 3, 4):
        t = time.perf_counter()
        imgs = [render_view(syn.boxes, c, ss)["absent"] for c in cams]
        dt = (time.perf_counter() - t) / views
        p = float(np.mean([psnr(a, b) for a, b in zip(imgs, ref)]))
        e = float(max(np.abs(a - b).max() for a, b in zip(imgs, ref)))
        print(f"| {ss}x{ss} | {dt:.3f} | {p:.2f} | {e:.3f} |")
        out.append({"supersample": ss, "s_per_view": round(dt, 4), "psnr_vs_ref": round(p, 2)})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", default=None, help="folder holding spinnerf_scene1/")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=192)
    args = ap.parse_args()

    from coin_cl.scene import load_scene
    from coin_cl.scene.synthetic import make_synthetic, write_synthetic

    rows = []
    res: dict = {"load_s": None, "synthetic_s": None, "n_views": None}
    d = shared_scene(args.data)
    if d is not None:
        t = time.perf_counter()
        sc = load_scene(d)
        res["load_s"] = round(time.perf_counter() - t, 3)
        res["n_views"] = len(sc)
        px = sum(c.width * c.height for c in sc.cameras)
        rows.append(
            (
                "load spinnerf_scene1 (1008x567, masks, priors, 73k pts)",
                len(sc),
                res["load_s"],
                f"{px / res['load_s'] / 1e6:.1f} Mpx/s",
            )
        )
    else:
        rows.append(("load spinnerf_scene1", 0, float("nan"), "data not found (set COIN_DATA)"))

    t = time.perf_counter()
    syn = make_synthetic(n_views=args.views, width=args.width, height=args.height, seed=0)
    t_make = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        write_synthetic(Path(tmp) / "scene", syn)
        t_write = time.perf_counter() - t
        t = time.perf_counter()
        load_scene(Path(tmp) / "scene")
        t_reload = time.perf_counter() - t
    res["synthetic_s"] = round(t_make + t_write, 3)
    res["synthetic_render_s"] = round(t_make, 3)
    res["synthetic_write_s"] = round(t_write, 3)
    res["synthetic_load_s"] = round(t_reload, 3)
    res["synthetic_views"] = args.views
    size = f"{args.width}x{args.height}"
    rows.append(
        (
            f"synthetic: ray cast {args.views} views {size} (present+absent, 2x2 ss)",
            args.views,
            round(t_make, 3),
            f"{args.views / t_make:.1f} views/s",
        )
    )
    rows.append(("synthetic: write SPIn-NeRF layout + COLMAP model", args.views, round(t_write, 3), ""))
    rows.append(("synthetic: load it back", args.views, round(t_reload, 3), ""))

    print(f"{'step':<66} {'views':>5} {'seconds':>8}  note")
    for name, n, s, note in rows:
        print(f"{name:<66} {n:>5} {s:>8}  {note}")
    res["supersample"] = supersample_table(syn, args.width, args.height)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
