"""Feature-warp benchmark: run time, error against the float64 twin,
bytes crossing host/device, and error against run time of the footprint / depth-tolerance knobs.

    python benchmarks/warp.py [--runs 3] [--quick]

Scene: a slanted textured plane seen by a 1008x567 reference camera k (the shared scene's focal
at that width); the target is the intermediate pose phi = interpolate_pose(k, n, 0.5) to a
second camera n rotated 12 degrees and moved 0.7 units. Points: N random positions of k's image
unprojected onto the plane (what the CLG stage passes: rendered depth unprojected), with k's
depth map as `src_depth`. Times are medians of --runs after a warm-up. "err" is max |x - x_ref| /
max |x_ref| against the twin: features where the weight is >= 1/4, weighted sums everywhere, the
gradient to the source features for a random cotangent. The knob table's error is against the
analytic answer (the plane's homography, OpenCV warpPerspective), mean absolute over covered
pixels. "bytes copied" is what a discrete device moves per forward+backward and the copies' device
time, measured on the discrete-memory path (Runtime(discrete=True): device-only buffers, counted
copies); on a unified-memory CPU device buffers alias the tensors and nothing is copied.

CLG part (`--clg`, or `--clg-only` to skip the op rows): the CLG stage per view on the shared
SPIn-NeRF scene (images_4 at --clg-scale, default 0.5 = 504x283). I^_n: the dataset's LaMa
inpaints (RGB_inpainted/) composited with the capture outside the mask. R_n and depths: stand-in
for Ref-GS (not merged yet): a short Scaffold-GS fit (--clg-gs-iters, default 300) on those
inpaints via `coin_cl.gs.trainer.make_trainer`, rendered with depth; P_k: its reference depth
unprojected by `coin_cl.pipeline.reference.reference_points` (the Ref-GS margin rule). Denoiser: the
scene prior (fixed --clg-prior-steps optimizer steps, cached); features: the analytic default.
Time per view against the number of DDIM steps; the consistency residual (mean |I_n - warp(I_k)|
over the support of view n's mask through P_k, `consistency_residual`) of I^_n (before), of the
unguided sample of the same seed and of the guided one (after).

The last line printed is one JSON object (warp_fwd_bwd_s_500k, warp_max_rel_err, clg_*, ...).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import cpu_model, git_commit, median_time  # noqa: E402

from coin_cl.engine import reference_warp as warp_reference  # noqa: E402
from coin_cl.engine.ops import warp  # noqa: E402
from coin_cl.engine.runtime import Runtime, get_runtime  # noqa: E402
from coin_cl.scene import Camera  # noqa: E402
from coin_cl.scene.conventions import interpolate_pose, make_viewmat, quat_wxyz_to_rotmat  # noqa: E402

W, H = 1008, 567
F_PX = 0.85 * W  # close to the shared SPIn-NeRF scene's images_4 focal at 1008 wide
NORMAL = np.array([0.15, -0.1, 1.0]) / np.linalg.norm([0.15, -0.1, 1.0])
D0 = 4.0
KNOBS = [
    ("bilinear, tol 0.01 (default)", "bilinear", 0.01),
    ("bilinear, tol 0.001", "bilinear", 0.001),
    ("bilinear, tol 0.05", "bilinear", 0.05),
    ("nearest, tol 0.01", "nearest", 0.01),
    ("nearest, tol 0.001", "nearest", 0.001),
    ("nearest, tol 0.05", "nearest", 0.05),
]


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return quat_wxyz_to_rotmat(np.concatenate([[math.cos(h)], math.sin(h) * axis]))


def _f32(a: np.ndarray) -> np.ndarray:
    """float32-exact values: the kernels and the twin then see the same cameras."""
    return np.asarray(a, np.float32).astype(np.float64)


def cameras() -> tuple[Camera, Camera]:
    K = _f32([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1]])
    k = Camera(K, _f32(make_viewmat(_rot([0, 1, 0], 4), [-0.2, 0.0, 0.0])), W, H, "k")
    n = Camera(K, make_viewmat(_rot([0.3, 1, 0], -12), [0.6, 0.1, 0.3]), W, H, "n")
    return k, Camera(K, _f32(interpolate_pose(k.viewmat, n.viewmat, 0.5)), W, H, "phi")


def plane_hit(cam: Camera, uv: np.ndarray) -> np.ndarray:
    rays = cam.unproject(uv, np.ones(len(uv))) - cam.center
    t = (D0 - cam.center @ NORMAL) / (rays @ NORMAL)
    return cam.center + t[:, None] * rays


def scene(n_points: int, channels: int, seed: int = 0):
    k, phi = cameras()
    rng = np.random.default_rng(seed)
    uv = rng.random((n_points, 2)) * [W, H]
    pts = torch.from_numpy(plane_hit(k, uv)).float()
    img = rng.random((H, W, channels)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 3.0) if channels <= 4 else img  # cv2 blurs <= 4 channels
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    z = (plane_hit(k, np.stack([xs.ravel(), ys.ravel()], 1)) - k.center) @ k.viewmat[2, :3]
    depth = torch.from_numpy(z.reshape(H, W)).float()
    return pts, k, phi, torch.from_numpy(img), depth


def homography_truth(k: Camera, phi: Camera, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """warpPerspective of k's image into phi through the plane, and the pixels it maps inside k."""
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    uv_d = np.array([[10.0, 10.0], [W - 10, 12.0], [W - 12, H - 9], [9.0, H - 11]])
    uv_s, _ = k.project(plane_hit(phi, uv_d))
    A = []
    for (x, y), (u, v) in zip(uv_d, uv_s):
        A += [[x, y, 1, 0, 0, 0, -u * x, -u * y, -u], [0, 0, 0, x, y, 1, -v * x, -v * y, -v]]
    Hm = np.linalg.svd(np.asarray(A))[2][-1].reshape(3, 3)
    T = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]])
    ref = cv2.warpPerspective(img, np.linalg.inv(T) @ Hm @ T, (W, H),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)  # fmt: skip
    q = Hm @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    su, sv = (q[0] / q[2]).reshape(H, W), (q[1] / q[2]).reshape(H, W)
    return ref, (su > 2) & (su < W - 2) & (sv > 2) & (sv < H - 2)


def run_op(mod, pts, k, phi, img, depth, v, rt=None, **kw):
    x = img.clone().requires_grad_(True)
    out, wt, z = mod.warp_features(pts, k.K, k.viewmat, x, phi.K, phi.viewmat, W, H, src_depth=depth,
                                   device=rt, **kw)  # fmt: skip
    (g,) = torch.autograd.grad(out, x, v)
    return out.detach(), wt, z, g


def rel(a, e, sel=None) -> float:
    a, e = a.double(), e.double()
    if sel is not None:
        a, e = a[sel], e[sel]
    return float((a - e).abs().max() / e.abs().max().clamp_min(1e-30))


def clg_part(args) -> dict:
    """The CLG rows (see the module docstring); returns the clg_* figures."""
    import logging
    from dataclasses import replace

    from coin_cl.diffusion import AnalyticFeatures, ScenePriorConfig, train_scene_prior

    from coin_cl.gs.trainer import TrainConfig, make_trainer
    from coin_cl.pipeline.clg import run_clg
    from coin_cl.pipeline.clg_config import CLGConfig
    from coin_cl.pipeline.reference import choose_reference, reference_points
    from coin_cl.scene import load_scene

    logging.basicConfig(level=logging.WARNING)
    data = Path(os.environ.get("COIN_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    scene = load_scene(data / "spinnerf_scene1")
    if args.clg_scale != 1.0:
        scene = scene.resized(args.clg_scale)
    work = Path(args.clg_work)
    work.mkdir(parents=True, exist_ok=True)
    train = [i for i in scene.train_idx if scene.masks[i].any()]
    lama = scene.priors.get("rgb", {})
    inp = [None] * len(scene)
    for i in train:
        m = scene.masks[i][..., None]
        inp[i] = np.where(m, lama[i], scene.images[i]).astype(np.float32) if i in lama else scene.images[i]
    k = choose_reference([scene.masks[i] for i in range(len(scene))], scene.cameras, train_idx=train)
    cam = scene.cameras[k]
    print(f"# CLG: {len(train)} masked training views at {cam.width}x{cam.height}, reference {k} "
          f"({cam.name}); I^_n = LaMa ({len(lama)} views)")  # fmt: skip
    t0 = time.perf_counter()
    renders, depths = [None] * len(scene), [None] * len(scene)
    cache = work / f"gs_{args.clg_gs_iters}_{args.clg_scale}.npz"
    if cache.is_file():
        z = np.load(cache)
        for i in train:
            renders[i], depths[i] = z[f"r{i}"], z[f"d{i}"]
    else:
        cfg = TrainConfig(iters=args.clg_gs_iters, progress=False, ckpt_every=0, export_ply=False, seed=0)
        tr = make_trainer(
            scene,
            train,
            [],
            cfg,
            out_dir=None,
            train_images=[scene.images[i] if inp[i] is None else inp[i] for i in range(len(scene))],
        )
        tr.train()
        for i in train:
            with torch.no_grad():
                r = tr.model.render(scene.cameras[i], tr.step, return_depth=True)
            renders[i] = r.image.clamp(0, 1).numpy().astype(np.float32)
            depths[i] = np.where(r.alpha.numpy() > 0.5, r.depth.numpy(), np.nan).astype(np.float32)
        np.savez(cache, **{f"r{i}": renders[i] for i in train}, **{f"d{i}": depths[i] for i in train})
    t_gs = time.perf_counter() - t0
    pk = reference_points(cam, depths[k], scene.masks[k])
    print(f"# R_n / depth stand-in: Scaffold-GS, {args.clg_gs_iters} iterations on the inpaints, "
          f"{t_gs:.0f} s; P_k: {len(pk)} points")  # fmt: skip
    t0 = time.perf_counter()
    pcfg = ScenePriorConfig(max_steps=args.clg_prior_steps, train_seconds=3600.0)
    prior = train_scene_prior([scene.images[i] for i in train], [scene.masks[i] for i in train], pcfg,
                              cache_dir=work, progress=False)  # fmt: skip
    print(f"# scene prior: {prior.info.get('steps')} steps ({time.perf_counter() - t0:.0f} s here, "
          f"cached: {prior.info.get('cached', False)})")  # fmt: skip
    feats = AnalyticFeatures()
    others = [i for i in train if i != k]
    views = [others[j] for j in np.linspace(0, len(others) - 1, min(args.clg_views, len(others))).astype(int)]
    base = CLGConfig(progress=False)
    sc = base.sampler
    steps_list = [int(x) for x in args.clg_steps.split(",")]
    print()
    print(f"CLG per view, {len(views)} views {views}, scene prior (work {prior.work_size} px), analytic features, "  # noqa: E501
          f"c = {sc.guidance_scale}, window [{sc.guidance_start}, {sc.guidance_end}), 'quad'. "
          "residual = mean |I_n - warp(I^_k)| over the supported mask pixels ([0, 1] RGB):")  # fmt: skip
    print()
    print(
        "| steps | guidance | s / view | residual I^_n (before) | residual output | energy I^_n | energy output |"  # noqa: E501
    )
    print("|---|---|---|---|---|---|---|")
    res: dict = {}
    for steps in steps_list:
        for c in (0.0, base.sampler.guidance_scale):
            out = work / f"clg_{steps}_{c}"
            import shutil

            shutil.rmtree(out, ignore_errors=True)
            cfg = replace(base, steps=steps, sampler=replace(base.sampler, guidance_scale=c))
            t0 = time.perf_counter()
            r = run_clg(
                k, views, scene.cameras, inp, renders, depths, scene.masks, pk, prior, feats, out, cfg
            )
            dt = (time.perf_counter() - t0) / len(views)
            recs = [v for v in r["views"].values() if "residual_after" in v]
            rb = float(np.nanmean([v["residual_before"] for v in recs]))
            ra = float(np.nanmean([v["residual_after"] for v in recs]))
            eb = float(np.mean([v["energy_input"] for v in recs]))
            ea = float(np.mean([v["energy_output"] for v in recs]))
            guide = f"c = {c}" if c else "none"
            print(f"| {steps} | {guide} | {dt:.2f} | {rb:.4f} | {ra:.4f} | {eb:.4f} | "
                  f"{ea:.4f} |", flush=True)  # fmt: skip
            res[f"clg_s_per_view_{steps}{'' if c else '_unguided'}"] = round(dt, 3)
            if steps == base.num_steps(prior):
                key = "" if c else "_unguided"
                res["clg_residual_before"] = round(rb, 5)
                res[f"clg_residual_after{key}"] = round(ra, 5)
                res[f"clg_energy_after{key}"] = round(ea, 5)
                res["clg_energy_before"] = round(eb, 5)
                if c:
                    res["clg_s_per_view"] = round(dt, 3)
    res["clg_steps_default"] = base.num_steps(prior)
    res["clg_gs_stand_in_s"] = round(t_gs, 1)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="100k only, no knob table")
    ap.add_argument("--clg", action="store_true", help="also run the CLG part")
    ap.add_argument("--clg-only", action="store_true", help="only the CLG part (no op rows)")
    ap.add_argument("--clg-scale", type=float, default=0.5)
    ap.add_argument("--clg-views", type=int, default=4, help="non-reference views guided")
    ap.add_argument("--clg-steps", default="10,25,50", help="DDIM step counts timed")
    ap.add_argument("--clg-gs-iters", type=int, default=300)
    ap.add_argument("--clg-prior-steps", type=int, default=150)
    ap.add_argument("--clg-work", default="/tmp/coin_cl_bench_clg", help="cache/output folder")
    args = ap.parse_args()
    rt = get_runtime()
    if args.clg_only:
        print(f"# coin-cl warp benchmark (CLG part): {rt.name}; CPU {cpu_model()}, {os.cpu_count()} cores; "
              f"commit {git_commit()}; {time.strftime('%Y-%m-%d %H:%M')}")  # fmt: skip
        res = clg_part(args)
        print()
        print(json.dumps({"device": rt.name, "cpu": cpu_model(), "commit": git_commit(), **res}))
        return
    print(f"# coin-cl warp benchmark: {rt.name}; CPU {cpu_model()}, {os.cpu_count()} cores; "
          f"commit {git_commit()}; {time.strftime('%Y-%m-%d %H:%M')}")  # fmt: skip
    print(f"# {W}x{H}, medians of {args.runs} runs after a warm-up; err = max|x - ref| / max|ref| (twin)")
    print()
    print("| points | C | valid | fwd s | fwd+bwd s | err feat | err weighted | err grad "
          "| bytes copied, copy time |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    res: dict[str, float] = {}
    errs = []
    sizes = [100_000] if args.quick else [100_000, 500_000]
    for n in sizes:
        for C in (3, 64):
            pts, k, phi, img, depth = scene(n, C)
            v = torch.randn(H, W, C, generator=torch.Generator().manual_seed(1))
            st: dict = {}

            def fwd(pts=pts, k=k, phi=phi, img=img, depth=depth, st=st):
                return warp.warp_features(pts, k.K, k.viewmat, img, phi.K, phi.viewmat, W, H,
                                          src_depth=depth, stats=st)  # fmt: skip

            t_f = median_time(fwd, args.runs)
            t_fb = median_time(lambda a=(pts, k, phi, img, depth, v): run_op(warp, *a), args.runs)
            out, wt, _, _ = run_op(warp, pts, k, phi, img, depth, v)
            copying = Runtime(rt.device, discrete=True)
            run_op(warp, pts, k, phi, img, depth, v, rt=copying)
            nbytes, copy_ms = copying.bytes_transferred, 1000 * copying.transfers.seconds
            e = [math.nan] * 3
            if not (n == 500_000 and C == 64):  # the twin would need several GiB there
                dbl = (pts.double(), k, phi, img.double(), depth.double())
                rout, rwt, _, _ = run_op(warp_reference, *dbl, v)
                full = rwt >= 0.25
                # The mean over a pixel's winners jumps where a point enters its footprint with a
                # tiny weight (1e-5 px of float32 rounding decides): the gradient is compared for a
                # cotangent on the pixels of weight >= 1/4, where the op is continuous.
                vf = v * full[..., None]
                g = run_op(warp, pts, k, phi, img, depth, vf)[3]
                rg = run_op(warp_reference, *dbl, vf.double())[3]
                e = [rel(out, rout, full), rel(out * wt[..., None], rout * rwt[..., None]), rel(g, rg)]
                errs += e
            print(f"| {n // 1000}k | {C} | {st['n_ok']} | {t_f:.3f} | {t_fb:.3f} | {e[0]:.2e} | {e[1]:.2e} | "
                  f"{e[2]:.2e} | {nbytes / 1e6:.1f} MB, {copy_ms:.1f} ms |", flush=True)  # fmt: skip
            res[f"warp_fwd_s_{n // 1000}k_c{C}"] = round(t_f, 4)
            res[f"warp_fwd_bwd_s_{n // 1000}k_c{C}"] = round(t_fb, 4)
            res[f"warp_bytes_{n // 1000}k_c{C}"] = nbytes
    res["warp_max_rel_err"] = max(errs)
    res["warp_fwd_bwd_s_500k"] = res.get("warp_fwd_bwd_s_500k_c3", math.nan)
    if not args.quick:
        n = 500_000
        pts, k, phi, img, depth = scene(n, 3)
        truth, inside = homography_truth(k, phi, img.numpy())
        v = torch.randn(H, W, 3, generator=torch.Generator().manual_seed(1))
        print()
        print(f"Error against run time, {n // 1000}k points, C = 3, {W}x{H}; error against the analytic "
              "homography warp (mean |x - truth| over covered pixels, image values in [0, 1]):")  # fmt: skip
        print()
        print("| knob | fwd s | fwd+bwd s | covered | mean err | p99 err |")
        print("|---|---|---|---|---|---|")
        for name, fp, tol in KNOBS:

            def fwd(fp=fp, tol=tol):
                return warp.warp_features(pts, k.K, k.viewmat, img, phi.K, phi.viewmat, W, H, src_depth=depth,
                                          footprint=fp, depth_tol=tol)  # fmt: skip

            t_f = median_time(fwd, args.runs)
            t_fb = median_time(lambda fp=fp, tol=tol: run_op(warp, pts, k, phi, img, depth, v, footprint=fp,
                                                             depth_tol=tol), args.runs)  # fmt: skip
            out, wt, _ = fwd()
            cov = (wt.numpy() > 0) & inside
            err = np.abs(out.numpy() - truth).max(-1)[cov]
            print(f"| {name} | {t_f:.3f} | {t_fb:.3f} | {cov.mean():.3f} | {err.mean():.4f} | "
                  f"{np.percentile(err, 99):.4f} |", flush=True)  # fmt: skip
            res[f"knob_{fp}_{tol}_mean_err"] = round(float(err.mean()), 5)
    if args.clg:
        res.update(clg_part(args))
    print()
    print(json.dumps({"device": rt.name, "cpu": cpu_model(), "commit": git_commit(), **res}))


if __name__ == "__main__":
    main()
