"""The CUDA peer of benchmarks/raster.py: the same scenes through gsplat's CUDA rasterizer.

    python benchmarks/raster_gsplat.py [--runs 5] [--scenes 10k,100k,500k] [--no-compare]

Same Gaussians (`garden_like` on the shared SPIn-NeRF cloud, seed 0), camera, image sizes and
cotangents as raster.py's `Case`; gsplat's `rasterization` with the settings that match coin-cl's
(classic mode, eps2d 0.3, near 0.01, far 1e10, no radius clip, tile 16, RGB, no background; packed,
its default), fwd and
fwd+bwd to means, quats, scales, opacities and colours, timed with torch.cuda.synchronize as medians
of --runs after a warm-up (the first call also JIT-builds gsplat's CUDA code: minutes). Unless
--no-compare, the image is also rendered by coin-cl on the default OpenCL device and the two are
compared (max |gsplat - coin-cl| / max |coin-cl|), so the table shows the same scene was drawn.

Needs a CUDA GPU, torch with CUDA and gsplat (docs/GPU.md says how to carry it there). The last line
printed is one JSON object (fwd_s_<scene>, fwd_bwd_s_<scene>, diff_<scene>, gpu, gsplat, commit).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402
from common import cpu_model, git_commit  # noqa: E402
from raster import Case, data_dir, named_scenes  # noqa: E402

from coin_cl.engine import constants as cst  # noqa: E402
from coin_cl.scene.ply import read_points_ply  # noqa: E402


def cuda_median(fn, runs: int) -> float:
    """Median wall time of `runs` calls of fn() after one warm-up, each ended by a synchronize."""
    fn()
    torch.cuda.synchronize()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


class Peer:
    """One raster.py scene on the GPU through gsplat."""

    def __init__(self, case: Case):
        dev = torch.device("cuda")
        self.case = case
        self.params = [t.detach().to(dev).requires_grad_(True) for t in case.gs.tensors()]
        self.viewmat = case.viewmat.to(dev)[None]
        self.K = case.K.to(dev)[None]
        self.v_img = case.v_img.to(dev)[None]
        self.v_alpha = case.v_alpha.to(dev)[None, ..., None]

    def forward(self):
        from gsplat import rasterization

        means, quats, scales, opac, colors = self.params
        img, alpha, _ = rasterization(
            means, quats, scales, opac, colors, self.viewmat, self.K, self.case.W, self.case.H,
            near_plane=cst.NEAR_PLANE, far_plane=cst.FAR_PLANE, eps2d=cst.EPS2D, radius_clip=0.0,
            tile_size=cst.TILE_SIZE, rasterize_mode="classic", render_mode="RGB",  # packed: its default
        )  # fmt: skip
        return img, alpha

    def fwd_bwd(self):
        img, alpha = self.forward()
        return torch.autograd.grad([img, alpha], self.params, [self.v_img, self.v_alpha])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scenes", default="10k,100k,500k", help="comma-separated raster.py scene names")
    ap.add_argument("--no-compare", action="store_true", help="skip the coin-cl render of each scene")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("raster_gsplat.py: no CUDA device visible to torch; run it on a machine with an NVIDIA GPU")
        return 2
    try:
        import gsplat
    except ImportError:
        print("raster_gsplat.py: gsplat is not installed; see docs/GPU.md for carrying its wheel")
        return 2
    pts, _ = read_points_ply(data_dir() / "sparse" / "0" / "points3D.ply")
    points = torch.from_numpy(pts)
    rt = None
    if not args.no_compare:
        from coin_cl.engine.runtime import get_runtime

        rt = get_runtime()
    gpu = torch.cuda.get_device_name()
    print(
        f"# gsplat {gsplat.__version__} (CUDA peer of benchmarks/raster.py) on {gpu}; "
        f"torch {torch.__version__}; host {cpu_model()}; commit {git_commit()}; "
        f"{time.strftime('%Y-%m-%d %H:%M')}"
    )
    print(f"# medians of {args.runs} runs after a warm-up; diff = max|gsplat - coin-cl| / max|coin-cl|")
    if rt is not None:
        print(f"# coin-cl device for the diff: {rt.name}")
    print()
    print("| scene | size | fwd s | fwd+bwd s | diff image | diff alpha |")
    print("|---|---|---|---|---|---|")
    summary: dict = {"gpu": gpu, "gsplat": gsplat.__version__, "torch": torch.__version__}
    summary["commit"] = git_commit()
    for name, n, W, H in named_scenes(args.scenes):
        case = Case(n, W, H, points, rt)
        peer = Peer(case)
        t_f = cuda_median(peer.forward, args.runs)
        t_fb = cuda_median(peer.fwd_bwd, args.runs)
        d_img = d_alpha = float("nan")
        if rt is not None:
            with torch.no_grad():
                img, alpha = (t[0].float().cpu() for t in peer.forward())
                ref_img, ref_alpha, _ = case.forward()
            d_img = float((img - ref_img).abs().max() / ref_img.abs().max().clamp_min(1e-30))
            d_alpha = float((alpha[..., 0] - ref_alpha).abs().max() / ref_alpha.abs().max().clamp_min(1e-30))
        print(f"| {name} | {W}x{H} | {t_f:.4f} | {t_fb:.4f} | {d_img:.2e} | {d_alpha:.2e} |", flush=True)
        summary.update({f"fwd_s_{name}": t_f, f"fwd_bwd_s_{name}": t_fb, f"diff_{name}": d_img})
    print()
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
