"""Rasterizer benchmark: run time next to error against the float64 torch twin.

    python benchmarks/raster.py [--quick] [--runs 5] [--device NAME|all] [--discrete] [--scenes 10k,100k]

`--device all` runs the table on every OpenCL device that builds kernels (simulators excluded) and
ends with a side-by-side table, so implementations are compared in one run on one machine.

Scenes follow gsplat's garden test data: points of the shared SPIn-NeRF SfM cloud, replicated with
jitter for larger N, scales U[1e-4, 0.02], random rotations, opacities U[0, 1], seen from the real
camera of view 0 (focal scaled to the image width). Times are medians of --runs after a warm-up,
measured in one run. Errors are max |x - x_ref| / max |x_ref| per quantity, stage by stage (each
stage gets the same float32 inputs as its twin, so the figure is the kernels' arithmetic error, not
the discontinuity of the integer radius/tile rule).

Copies: "copy MB/step" and "copy ms/step" are what crossed between torch and the device per
forward+backward on the path benchmarked (the copies' device time from OpenCL event profiling;
0 on a host-unified-memory device, which aliases the tensors). `--discrete` forces the
discrete-memory path (device-only buffers, explicit copies: COIN_CL_DISCRETE=1) on any device, as a
discrete GPU runs it; "bytes copied (discrete path)" is measured on that path in every run.

The last line printed is one JSON object (fwd_s_500k, fwd_bwd_s_500k, fwd_bwd_s_100k_512,
max_rel_err_fwd, max_rel_err_grad, ...).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import cpu_model, git_commit, median_time  # noqa: E402

from coin_cl.engine import ops, reference  # noqa: E402
from coin_cl.engine.runtime import Runtime, get_runtime  # noqa: E402
from coin_cl.scene.conventions import invert_rigid, llff_to_camtoworld  # noqa: E402
from coin_cl.scene.ply import read_points_ply  # noqa: E402
from coin_cl.testing import garden_like  # noqa: E402

SCENES = [("10k", 10_000, 256, 256), ("100k", 100_000, 512, 512), ("500k", 500_000, 1008, 567)]
# Only by name (--scenes): sizes for a GPU, minutes per run on a 2-core CPU.
LARGE_SCENES = [
    ("1M", 1_000_000, 1008, 567), ("100k-1080p", 100_000, 1920, 1080), ("500k-1080p", 500_000, 1920, 1080),
    ("1M-1080p", 1_000_000, 1920, 1080),
]  # fmt: skip


def named_scenes(names: str) -> list[tuple[str, int, int, int]]:
    """The scenes of SCENES and LARGE_SCENES named in a comma-separated list, in that order."""
    wanted, known = names.split(","), [s[0] for s in SCENES + LARGE_SCENES]
    if set(wanted) - set(known):
        raise SystemExit(f"--scenes: unknown {sorted(set(wanted) - set(known))}; known: {known}")
    return [s for s in SCENES + LARGE_SCENES if s[0] in wanted]


KNOBS = [
    ("default", {}),
    ("alpha_thr=1/128", {"ALPHA_THRESHOLD": "(1.0f/128.0f)"}),
    ("alpha_thr=1/32", {"ALPHA_THRESHOLD": "(1.0f/32.0f)"}),
    ("T_min=1e-3", {"TRANSMITTANCE_MIN": "1e-3f"}),
    ("T_min=1e-2", {"TRANSMITTANCE_MIN": "1e-2f"}),
    ("acc=double", {"ACC_DOUBLE": 1}),
    ("bwd=atomics (not deterministic)", {"DETERMINISTIC": 0}),
    ("exp=native_exp", {"EXPF": "native_exp"}),
]


def data_dir() -> Path:
    env = os.environ.get("COIN_DATA")
    d = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    d = d / "spinnerf_scene1"
    if not d.is_dir():
        raise FileNotFoundError(f"{d} not found: set COIN_DATA to the folder holding spinnerf_scene1")
    return d


def camera(width: int, height: int):
    d = data_dir()
    c2w, hwf, _ = llff_to_camtoworld(np.load(d / "poses_bounds.npy"))
    viewmat = torch.tensor(invert_rigid(c2w[0]), dtype=torch.float32)
    f = hwf[0, 2] / 4 * width / 1008  # images_4 focal, scaled to the width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
    return viewmat, K


def rel_err(a: torch.Tensor, e: torch.Tensor) -> float:
    a, e = a.detach().double(), e.detach().double()
    return float((a - e).abs().max() / e.abs().max().clamp_min(1e-30))


class Case:
    def __init__(
        self, n: int, width: int, height: int, points: torch.Tensor, rt: Runtime, scale_mult: float = 1.0
    ):
        self.rt = rt
        self.n, self.W, self.H = n, width, height
        self.gs = garden_like(points, n, seed=0)
        self.gs.scales *= scale_mult
        self.viewmat, self.K = camera(width, height)
        g = torch.Generator().manual_seed(1)
        self.v_img = torch.randn(height, width, 3, generator=g)
        self.v_alpha = torch.randn(height, width, generator=g)
        self.params = [t.clone().requires_grad_(True) for t in self.gs.tensors()]

    def forward(self, defines=None, rt=None):
        rt = rt or self.rt
        means, quats, scales, opac, colors = self.params
        m2, con, dep, rad = ops.project(means, quats, scales, self.viewmat, self.K, self.W, self.H, device=rt)
        stats: dict = {}
        img, alpha = ops.rasterize_to_pixels(
            m2, con, opac, colors, dep, rad, self.W, self.H, stats=stats, device=rt, defines=defines
        )
        return img, alpha, stats

    def fwd_bwd(self, defines=None, rt=None):
        img, alpha, _ = self.forward(defines, rt)
        return torch.autograd.grad([img, alpha], self.params, [self.v_img, self.v_alpha])

    def pairs(self) -> int:
        return self.forward()[2]["n_pairs"]

    def stage_inputs(self):
        """Projected float32 inputs (as the rasterize kernel sees them), for the twin in float64."""
        with torch.no_grad():
            m2, con, dep, rad = ops.project(
                *self.gs.tensors()[:3], self.viewmat, self.K, self.W, self.H, device=self.rt
            )
        return m2, con, dep, rad

    def reference_stage(self):
        """Twin outputs and gradients of the rasterize stage, and of the projection stage."""
        m2, con, dep, rad = self.stage_inputs()
        xs = [t.double().requires_grad_(True) for t in (m2, con, self.gs.opacities, self.gs.colors)]
        img, alpha = reference.rasterize_to_pixels(
            xs[0], xs[1], xs[2], xs[3], dep.double(), rad, self.W, self.H
        )
        grads = torch.autograd.grad([img, alpha], xs, [self.v_img.double(), self.v_alpha.double()])
        return (img.detach(), alpha.detach()), grads

    def kernel_stage(self, defines=None):
        m2, con, dep, rad = self.stage_inputs()
        xs = [t.clone().requires_grad_(True) for t in (m2, con, self.gs.opacities, self.gs.colors)]
        img, alpha = ops.rasterize_to_pixels(
            xs[0], xs[1], xs[2], xs[3], dep, rad, self.W, self.H, defines=defines, device=self.rt
        )
        grads = torch.autograd.grad([img, alpha], xs, [self.v_img, self.v_alpha])
        return (img.detach(), alpha.detach()), grads

    def projection_errors(self) -> tuple[float, float]:
        """(forward, gradient) error of the projection kernel against its twin on common visibles."""
        means, quats, scales = (t.double().requires_grad_(True) for t in self.gs.tensors()[:3])
        out_r = reference.project(
            means, quats, scales, self.viewmat.double(), self.K.double(), self.W, self.H
        )
        f32 = [t.detach().float().requires_grad_(True) for t in (means, quats, scales)]
        out_k = ops.project(*f32, self.viewmat, self.K, self.W, self.H, device=self.rt)
        both = (out_r[3] > 0) & (out_k[3] > 0)
        fwd = max(rel_err(k[both], r[both].detach()) for k, r in zip(out_k[:3], out_r[:3]))
        g = torch.Generator().manual_seed(2)
        cot = [
            torch.randn(t.shape, generator=g, dtype=torch.float64) * both.reshape(-1, *[1] * (t.dim() - 1))
            for t in out_r[:3]
        ]
        gr = torch.autograd.grad(out_r[:3], [means, quats, scales], cot)
        gk = torch.autograd.grad(out_k[:3], f32, [c.float() for c in cot])
        return fwd, max(rel_err(a, b) for a, b in zip(gk, gr))


def devices(request: str | None) -> list[Runtime]:
    """The runtimes to benchmark: the default, a named one, or every device that builds kernels."""
    from coin_cl.engine.devices import all_devices, default_rank, device_label, probe_device, working_devices

    if request != "all":
        return [get_runtime(request)]
    for _, d in all_devices():
        if default_rank(d)[0] < 9 and not probe_device(d).ok:
            print(f"# skipped {device_label(d)}: {probe_device(d).message}")
    return [Runtime(d) for d in working_devices()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="10k and 100k scenes only, no knob table")
    ap.add_argument("--twin-max-n", type=int, default=100_000, help="largest N checked against the twin")
    ap.add_argument("--device", default=None, help="device name substring, or 'all' (default: the default)")
    ap.add_argument("--discrete", action="store_true", help="device-only buffers and counted copies")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: all, or --quick's)")
    ap.add_argument(
        "--split",
        action="store_true",
        help="only: where one fwd+bwd's time goes (kernels by name, copies, host) per scene",
    )
    args = ap.parse_args()
    if args.discrete:  # before the first runtime is made
        os.environ["COIN_CL_DISCRETE"] = "1"
    pts, _ = read_points_ply(data_dir() / "sparse" / "0" / "points3D.ply")
    points = torch.from_numpy(pts)
    print(
        f"# coin-cl rasterizer benchmark: {cpu_model()}, {os.cpu_count()} cores; commit {git_commit()}; "
        f"{time.strftime('%Y-%m-%d %H:%M')}"
    )
    runtimes = devices(args.device)
    if args.split:
        print(json.dumps([split_device(rt, args, points) for rt in runtimes]))
        return
    summaries = [run_device(rt, args, points) for rt in runtimes]
    if len(summaries) == 1:
        print(json.dumps(summaries[0]))
        return
    print()
    print("Side by side (same run, same machine):")
    print()
    keys = [k for k in summaries[0] if k.startswith("fwd") or k.startswith("max_rel")]
    print("| device | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for s in summaries:
        print(f"| {s['device']} | " + " | ".join(f"{s[k]:.3g}" for k in keys) + " |")
    print()
    print(json.dumps({"cpu": cpu_model(), "commit": git_commit(), "devices": summaries}))


def split_device(rt: Runtime, args: argparse.Namespace, points: torch.Tensor) -> dict:
    """Where a forward+backward's wall time goes on one device: each kernel's device time and the
    copies' (OpenCL event profiling; every launch then waits for its event, so the wall time is
    that of a serialised step), the rest being host work (torch, numpy, Python, launches); then the
    host functions that take most of it (cProfile, own time). Medians over --runs after a warm-up."""
    import cProfile
    import pstats

    rt = Runtime(rt.device, discrete=rt.discrete)
    rt.profile = True  # the queue already profiles on the discrete path; on unified memory:
    if not rt.discrete:
        import pyopencl as cl

        rt.queue = cl.CommandQueue(rt.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
    path = "discrete" if rt.discrete else "unified"
    print(f"\n## {rt.name}: where one fwd+bwd goes ({path} memory path)\n")
    out: dict = {"device": rt.name}
    scenes = named_scenes(args.scenes) if args.scenes else SCENES
    for name, n, W, H in scenes:
        case = Case(n, W, H, points, rt)
        case.fwd_bwd()
        walls, kernels, copies = [], {}, []
        for _ in range(args.runs):
            rt.kernel_times.clear()
            before = rt.transfers.snapshot()
            t0 = time.perf_counter()
            case.fwd_bwd()
            walls.append(time.perf_counter() - t0)
            copies.append(rt.transfers.delta(rt.transfers.snapshot(), before)["seconds"])
            for k, ts in rt.kernel_times.items():
                kernels.setdefault(k, []).append(sum(ts))
        wall = statistics.median(walls)
        kern = {k: statistics.median(v) for k, v in kernels.items()}
        copy = statistics.median(copies)
        host = wall - sum(kern.values()) - copy
        print(f"### {name} ({W}x{H}): {wall * 1e3:.1f} ms serialised\n")
        print("| part | ms | share |\n|---|---|---|")
        for k, t in sorted(kern.items(), key=lambda kv: -kv[1]):
            print(f"| kernel {k} | {t * 1e3:.2f} | {t / wall:.0%} |")
        print(f"| copies | {copy * 1e3:.2f} | {copy / wall:.0%} |")
        print(f"| host (rest) | {host * 1e3:.2f} | {host / wall:.0%} |\n")
        rt.profile = False  # launches no longer wait: the host's own time, not the device's
        prof = cProfile.Profile()
        prof.enable()
        case.fwd_bwd()
        prof.disable()
        print("host functions, own time of one fwd+bwd (cProfile):\n```")
        pstats.Stats(prof).sort_stats("tottime").print_stats(12)
        print("```")
        rt.profile = True
        out[name] = {"wall_ms": wall * 1e3, "kernels_ms": {k: t * 1e3 for k, t in kern.items()},
                     "copies_ms": copy * 1e3, "host_ms": host * 1e3}  # fmt: skip
    return out


def run_device(rt: Runtime, args: argparse.Namespace, points: torch.Tensor) -> dict:
    """The scene table (and knob tables unless --quick) on one device; returns its summary."""
    print()
    print(f"## {rt.name} ({rt.device.version}; {'discrete' if rt.discrete else 'unified'} memory path)")
    print()
    print(f"# medians of {args.runs} runs after a warm-up; err = max|x - ref| / max|ref| (float64 twin)")
    print()
    cols = [
        "scene", "size", "pairs", "visible", "fwd s", "fwd+bwd s", "pairs/s (fwd)", "err img", "err grad",
        "err proj", "err proj grad", "copy MB/step", "copy ms/step", "bytes copied (discrete path)",
    ]  # fmt: skip
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    summary: dict = {"device": rt.name, "cpu": cpu_model(), "commit": git_commit(), "discrete": rt.discrete}
    err_f, err_g = [], []
    cases = {}
    scenes = SCENES if not args.quick else SCENES[:2]
    if args.scenes:
        scenes = named_scenes(args.scenes)
    for name, n, W, H in scenes:
        case = cases[name] = Case(n, W, H, points, rt)
        t_f = median_time(case.forward, args.runs)
        before = rt.transfers.snapshot()
        t_fb = median_time(case.fwd_bwd, args.runs)
        crossed = rt.transfers.delta(rt.transfers.snapshot(), before)  # the warm-up and the runs
        steps = args.runs + 1
        copy_mb, copy_ms = crossed["bytes"] / 1e6 / steps, crossed["seconds"] * 1e3 / steps
        _, _, stats = case.forward()
        # What a discrete GPU moves per forward+backward: measured on the discrete path.
        rt_copy = rt if rt.discrete else Runtime(rt.device, discrete=True)
        copy_before = rt_copy.transfers.snapshot()
        case.fwd_bwd(rt=rt_copy)
        copy_bytes = rt_copy.transfers.bytes - copy_before["bytes"]
        e_img = e_grad = e_p = e_pg = float("nan")
        if n <= args.twin_max_n:
            (ri, ra), rg = case.reference_stage()
            (ki, ka), kg = case.kernel_stage()
            e_img = max(rel_err(ki, ri), rel_err(ka, ra))
            e_grad = max(rel_err(a, b) for a, b in zip(kg, rg))
            e_p, e_pg = case.projection_errors()
            err_f += [e_img, e_p]
            err_g += [e_grad, e_pg]
            case.reference = (ri, ra, rg)
        print(
            f"| {name} | {W}x{H} | {stats['n_pairs']} | {stats['n_visible']} | {t_f:.3f} | {t_fb:.3f} | "
            f"{stats['n_pairs'] / t_f:.3g} | {e_img:.2e} | {e_grad:.2e} | {e_p:.2e} | {e_pg:.2e} | "
            f"{copy_mb:.2f} | {copy_ms:.2f} | {copy_bytes / 1e6:.1f} MB |"
        )
        summary[f"copy_mb_per_step_{name}"] = copy_mb
        summary[f"copy_ms_per_step_{name}"] = copy_ms
        summary[f"fwd_s_{name}"] = t_f
        summary[f"fwd_bwd_s_{name}"] = t_fb
        summary[f"pairs_{name}"] = stats["n_pairs"]
    summary["fwd_bwd_s_100k_512"] = summary.get("fwd_bwd_s_100k")
    summary["max_rel_err_fwd"] = max(err_f, default=float("nan"))
    summary["max_rel_err_grad"] = max(err_g, default=float("nan"))

    if not args.quick and "100k" in cases:
        # Two scenes: the sparse garden-like one above, and a dense one (splats 50x larger, so
        # they overlap and pixels saturate) where the transmittance and alpha knobs matter.
        dense = Case(100_000, 512, 512, points, rt, scale_mult=50.0)
        for label_scene, case in (("garden-like", cases["100k"]), ("dense (scales x50)", dense)):
            (ri, ra), rg = case.reference_stage()
            print()
            print(
                f"Error against run time, 100k Gaussians at 512x512, {label_scene} scene, "
                f"{case.pairs()} pairs (rasterize stage; twin = default semantics):"
            )
            print()
            print("| knob | fwd s | fwd+bwd s | err img | err grad (means2d, conics, opacities, colours) |")
            print("|---|---|---|---|---|")
            for label, defines in KNOBS:
                t_f = median_time(lambda d=defines, c=case: c.forward(d), args.runs)
                t_fb = median_time(lambda d=defines, c=case: c.fwd_bwd(d), args.runs)
                (ki, ka), kg = case.kernel_stage(defines)
                e_img = max(rel_err(ki, ri), rel_err(ka, ra))
                e_g = ", ".join(f"{rel_err(a, b):.1e}" for a, b in zip(kg, rg))
                print(f"| {label} | {t_f:.3f} | {t_fb:.3f} | {e_img:.2e} | {e_g} |")
                key = f"knob_{'dense_' if case is dense else ''}{label}"
                summary[key] = {"fwd_s": t_f, "fwd_bwd_s": t_fb, "err_img": e_img}
    print()
    return summary


if __name__ == "__main__":
    main()
