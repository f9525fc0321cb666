"""Benchmark: how many (tile, splat) pairs an exact ellipse-against-tile test would save
over binning's opacity-aware box, on the splats of a trained model's views.

Binning sends each splat to the 16x16 tiles of its box (the bounding box of the ellipse outside which
o exp(-q/2) < 1/255, padded by a pixel, capped by the 3-sigma radius); the rasterizers then work per
(tile, splat) pair. An AccuTile-style test would keep only the tiles that ellipse touches (padded the
same way). This counts both, per view, in float64 numpy (no kernel change): if the saving is small,
the test is not worth building. Usage:
    python benchmarks/tile_pairs.py RUN/2_refgs/gs [--views 6]
(a trainer checkpoint folder: ckpt.pt and cameras.json). Last line one JSON object.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import cpu_model, git_commit  # noqa: E402

from coin_cl.checkpoint import load_checkpoint  # noqa: E402
from coin_cl.engine import constants as cst  # noqa: E402
from coin_cl.engine.reference import splat_extents  # noqa: E402
from coin_cl.gs.model_kinds import model_from_state  # noqa: E402
from coin_cl.gs.trainer import cameras_from_json  # noqa: E402


def pair_counts(m2: np.ndarray, con: np.ndarray, op: np.ndarray, rad: np.ndarray, w: int, h: int) -> tuple:
    """(box pairs, ellipse pairs, visible splats) of one view's projected splats (float64)."""
    ts = cst.TILE_SIZE
    tx_n, ty_n = math.ceil(w / ts), math.ceil(h / ts)
    ext = splat_extents(torch.from_numpy(con), torch.from_numpy(op), torch.from_numpy(rad)).numpy()
    ok = ext[:, 0] >= 0
    ex, ey = np.minimum(ext[:, 0], rad), np.minimum(ext[:, 1], rad)
    x0 = np.clip(np.floor((m2[:, 0] - ex) / ts), 0, tx_n)
    x1 = np.clip(np.ceil((m2[:, 0] + ex) / ts), 0, tx_n)
    y0 = np.clip(np.floor((m2[:, 1] - ey) / ts), 0, ty_n)
    y1 = np.clip(np.ceil((m2[:, 1] + ey) / ts), 0, ty_n)
    area = np.where(ok, np.maximum(x1 - x0, 0) * np.maximum(y1 - y0, 0), 0)
    a, b, c = con[:, 0], con[:, 1], con[:, 2]
    det = np.where(ok, a * c - b * b, 1.0)
    k2 = 2 * np.log(np.where(ok, op, 1.0) / cst.ALPHA_THRESHOLD).clip(0)
    sxx, syy, sxy = c / det, a / det, -b / det
    ky = np.sqrt(k2 * syy)
    dys = np.sqrt(k2) * sxy / np.sqrt(np.maximum(sxx, 1e-300))  # y of the ellipse's rightmost point
    ell = 0
    idx = np.nonzero(area > 0)[0]
    for ty in range(ty_n):
        s = idx[(y0[idx] <= ty) & (ty < y1[idx])]
        if len(s) == 0:
            continue
        # the tile row's band, padded by a pixel, clipped to the ellipse's own y range
        lo = np.maximum(ty * ts - 1 - m2[s, 1], -ky[s])
        hi = np.minimum(ty * ts + ts + 1 - m2[s, 1], ky[s])

        def edge(dy, sign, s=s):
            half = np.sqrt(np.maximum(0.0, a[s] * k2[s] - det[s] * dy * dy)) / a[s]
            return -b[s] * dy / a[s] + sign * half

        xr = edge(np.clip(dys[s], lo, hi), 1) + 1
        xl = edge(np.clip(-dys[s], lo, hi), -1) - 1
        t0 = np.maximum(np.clip(np.floor((m2[s, 0] + xl) / ts), 0, tx_n), x0[s])
        t1 = np.minimum(np.clip(np.ceil((m2[s, 0] + xr) / ts), 0, tx_n), x1[s])
        ell += int(np.where(lo <= hi, np.maximum(t1 - t0, 0), 0).sum())
    return int(area.sum()), ell, int(ok.sum())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("ckpt_dir", type=Path, help="trainer checkpoint folder (ckpt.pt, cameras.json)")
    ap.add_argument("--views", type=int, default=6, help="training views to count (the first N)")
    args = ap.parse_args()
    for name in ("ckpt.pt", "cameras.json"):
        if not (args.ckpt_dir / name).is_file():
            ap.error(f"{args.ckpt_dir / name} not found: pass a trainer checkpoint folder")
    model = model_from_state(load_checkpoint(args.ckpt_dir / "ckpt.pt")["model"])
    cams = cameras_from_json(json.loads((args.ckpt_dir / "cameras.json").read_text())["train"])

    import coin_cl.engine.ops.rasterize as rz

    seen: dict = {}
    real = rz.bin_tiles

    def spy(m2, con, op, dep, rad, w, h, *a, **k):  # the splats exactly as the renderer bins them
        seen.update(m2=m2.double().numpy(), con=con.double().numpy(), op=op.double().numpy(),
                    rad=rad.numpy().astype(np.float64), w=w, h=h)  # fmt: skip
        return real(m2, con, op, dep, rad, w, h, *a, **k)

    rz.bin_tiles = spy
    print(f"# tile pairs: box vs ellipse; {args.ckpt_dir}; CPU {cpu_model()}; commit {git_commit()}")
    print("\n| view | splats | visible | box pairs | ellipse pairs | ratio |\n|---|---|---|---|---|---|")
    tot_box = tot_ell = 0
    for cam in cams[: args.views]:
        with torch.no_grad():
            model.render(cam, 10**9)
        box, ell, vis = pair_counts(seen["m2"], seen["con"], seen["op"], seen["rad"], seen["w"], seen["h"])
        tot_box, tot_ell = tot_box + box, tot_ell + ell
        print(f"| {cam.name} | {len(seen['op'])} | {vis} | {box} | {ell} | {ell / max(box, 1):.3f} |")
    result = {"box_pairs": tot_box, "ellipse_pairs": tot_ell, "ratio": tot_ell / max(tot_box, 1),
              "views": min(args.views, len(cams)), "cpu": cpu_model(), "commit": git_commit()}  # fmt: skip
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
