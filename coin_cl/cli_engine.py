"""`coin-cl demo` and `coin-cl doctor`: the engine's own subcommands."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import time
from pathlib import Path

log = logging.getLogger("coin_cl.demo")


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the engine and the current pipeline on embedded scenes (no data or download needed)",
    )
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--frames", type=int, default=12, help="turntable frames")
    p.add_argument("--size", type=int, nargs=2, default=(480, 320), metavar=("W", "H"))
    p.add_argument("--steps", type=int, default=400, help="training steps on the synthetic room")
    p.add_argument("--render-only", action="store_true", help="only the turntable (seconds)")
    p.add_argument("--device", default=None, help="OpenCL device name substring")
    p.set_defaults(func=run_demo)
    d = sub.add_parser("doctor", help="OpenCL platforms/devices and what is installed")
    d.add_argument(
        "--working",
        action="store_true",
        help="only print the devices that build and run kernels, one 'platform / device' per line "
        "(usable as COIN_CL_DEVICE); exit 1 when there is none",
    )
    d.set_defaults(func=run_doctor)


def embedded_scene(n: int = 60_000, seed: int = 0):
    """A procedural scene: a textured torus knot of Gaussians over a checkered floor disc."""
    import torch

    from coin_cl.engine import Gaussians

    g = torch.Generator().manual_seed(seed)
    k = n * 2 // 3
    t = torch.rand(k, generator=g) * 2 * math.pi
    p, q = 2, 3
    r = torch.cos(q * t) + 2
    knot = torch.stack([r * torch.cos(p * t), -torch.sin(q * t), r * torch.sin(p * t)], 1) * 0.35
    knot = knot + torch.randn(k, 3, generator=g) * 0.06
    hue = (t / (2 * math.pi))[:, None]
    knot_col = 0.5 + 0.5 * torch.cos(2 * math.pi * (hue + torch.tensor([0.0, 0.33, 0.67])))
    m = n - k
    rad = 1.6 * torch.sqrt(torch.rand(m, generator=g))
    ang = torch.rand(m, generator=g) * 2 * math.pi
    floor = torch.stack([rad * torch.cos(ang), torch.full((m,), 0.75), rad * torch.sin(ang)], 1)
    check = ((floor[:, 0] * 3).floor() + (floor[:, 2] * 3).floor()) % 2
    floor_col = (0.25 + 0.5 * check)[:, None].expand(m, 3) * torch.tensor([1.0, 0.95, 0.85])
    means = torch.cat([knot, floor])
    scales = torch.cat([torch.full((k, 3), 0.025), torch.tensor([0.04, 0.004, 0.04]).expand(m, 3)])
    scales = scales * (0.6 + 0.8 * torch.rand(n, 3, generator=g))
    return Gaussians(
        means=means,
        quats=torch.cat([torch.randn(k, 4, generator=g), torch.tensor([[1.0, 0, 0, 0]]).expand(m, 4)]),
        scales=scales,
        opacities=0.5 + 0.5 * torch.rand(n, generator=g),
        colors=torch.cat([knot_col, floor_col]).clamp(0, 1),
    )


def orbit_viewmat(angle: float, radius: float = 4.0, height: float = -1.2):
    """World-to-camera of a camera on a circle around the origin, looking at it (OpenCV axes)."""
    import torch

    eye = torch.tensor([radius * math.sin(angle), height, -radius * math.cos(angle)])
    fwd = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), fwd)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm


def run_demo(args: argparse.Namespace) -> int:
    """Part 1: render a procedural Gaussian scene (the engine). Part 2: the synthetic room with
    ground truth: reconstruct it from object-present views with the object masked out of the loss,
    render the object-absent test views and score them (the masked-reconstruction baseline)."""
    from coin_cl.engine.runtime import get_runtime
    from coin_cl.scene.io import write_text

    rt = get_runtime(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"device": rt.name, "turntable": demo_turntable(args, out / "turntable")}
    if not args.render_only:
        summary["room"] = demo_room(args, out / "room")
    write_text(out / "demo.json", json.dumps(summary, indent=2))
    print(json.dumps(summary))
    print(f"wrote {out}/ (turntable/, room/, demo.json)")
    return 0


def demo_turntable(args: argparse.Namespace, out: Path) -> dict:
    import imageio.v3 as iio
    import torch
    from tqdm import tqdm

    import coin_cl
    from coin_cl.engine.runtime import get_runtime
    from coin_cl.scene.io import atomic_write, write_png

    rt = get_runtime(args.device)
    W, H = args.size
    gs = embedded_scene()
    f = 0.9 * W
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    out.mkdir(parents=True, exist_ok=True)
    log.info("demo: embedded procedural scene, %d Gaussians, %dx%d, device %s", len(gs.means), W, H, rt.name)
    frames, times, pairs = [], [], []
    for i in tqdm(range(args.frames), desc="rendering turntable"):
        vm = orbit_viewmat(2 * math.pi * i / args.frames)
        t0 = time.perf_counter()
        img, alpha, depth, meta = coin_cl.rasterize(
            *gs.tensors(),
            vm,
            K,
            W,
            H,
            background=torch.tensor([0.06, 0.07, 0.1]),
            return_depth=True,
            device=rt,
        )
        times.append(time.perf_counter() - t0)
        pairs.append(meta["n_pairs"])
        frame = (img.clamp(0, 1) * 255).to(torch.uint8).numpy()
        frames.append(frame)
        write_png(out / f"frame_{i:03d}.png", frame)
    atomic_write(
        out / "turntable.gif", lambda p: iio.imwrite(p, frames, extension=".gif", duration=80, loop=0)
    )
    return {
        "gaussians": len(gs.means),
        "size": [W, H],
        "frames": args.frames,
        "median_render_s": sorted(times)[len(times) // 2],
        "median_pairs": sorted(pairs)[len(pairs) // 2],
    }


def demo_room(args: argparse.Namespace, out: Path) -> dict:
    import torch

    from coin_cl import load_scene
    from coin_cl.evaluation import evaluate_folder
    from coin_cl.gs.trainer import TrainConfig, make_trainer, scaled_model_config
    from coin_cl.scene.io import to_uint8, write_png
    from coin_cl.scene.synthetic import write_synthetic

    log.info(
        "demo: synthetic room; 3DGS trained on the object-present views with the object masked out "
        "of the loss (the masked-reconstruction baseline; CoIn's inpainting stages are not in this "
        "version), scored on the object-absent ground-truth views"
    )
    scene_dir = out / "scene"
    if not (scene_dir / "views.txt").is_file():
        write_synthetic(scene_dir, coverage=180, n_views=24, width=192, height=144, seed=0)
    scene = load_scene(scene_dir)
    cfg = TrainConfig(model="3dgs", iters=args.steps, ckpt_every=200)
    trainer = make_trainer(
        scene, scene.train_idx, scene.test_idx, cfg, out / "train",
        model_cfg=scaled_model_config("3dgs", args.steps), exclude_masks=True, device=args.device,
    )  # fmt: skip
    res = trainer.train()
    pred = out / "pred"
    pred.mkdir(parents=True, exist_ok=True)
    for view in trainer.test_views:
        with torch.no_grad():
            r = trainer.model.render(view.camera, trainer.step)
        write_png(pred / view.camera.name, to_uint8(r.image.clamp(0, 1).numpy()))
    doc = evaluate_folder(pred, scene_dir, out / "eval")
    agg = doc["mean"]
    return {
        "steps": res["step"],
        "train_s": res["train_seconds"],
        "gaussians": res["n"],
        "test_psnr": agg.get("psnr"),
        "test_m_psnr": agg.get("m_psnr"),
        "what": "masked-reconstruction baseline (object pixels excluded from the loss)",
    }


def run_doctor(args: argparse.Namespace) -> int:
    """Print versions and, for every OpenCL device, whether it builds and runs kernels; exit 1 when
    none does (with what to install)."""
    from importlib import metadata

    from coin_cl.engine import runtime

    if args.working:
        labels = [runtime.device_label(d) for d in runtime.working_devices()]
        print("\n".join(labels))
        return 0 if labels else 1
    omp = os.environ.get("OMP_WAIT_POLICY")
    print(f"python {platform.python_version()} on {platform.machine()}, OMP_WAIT_POLICY={omp}")
    for pkg in (
        "torch",
        "numpy",
        "pyopencl",
        "pocl-binary-distribution",
        "intel-opencl-rt",
        "pycolmap",
        "opencv-contrib-python-headless",
        "scikit-image",
    ):
        try:
            print(f"  {pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            print(f"  {pkg}: not installed")
    print(f"OCL_ICD_VENDORS={os.environ.get('OCL_ICD_VENDORS', '(unset)')}")
    devices = [d for _, d in runtime.all_devices()]
    if not devices:
        print(f"OpenCL: no platform found; {runtime._INSTALL_HINT}")
        return 1
    print("OpenCL devices (probe = build and run a tiny kernel):")
    working = []
    for d in devices:
        probe = runtime.probe_device(d)
        rank, why = runtime.default_rank(d)
        state = f"works ({probe.seconds:.2f} s to build and run)" if probe.ok else f"FAILS: {probe.message}"
        print(f"  {runtime.device_label(d)}  [{d.version}]")
        print(f"    probe: {state}")
        if probe.ok:
            working.append((rank, why, d))
            print(
                f"    float atomics: {runtime.probe_float_atomics(d)}; "
                f"fp64: {'cl_khr_fp64' in d.extensions}; "
                f"global memory {d.global_mem_size / 2**30:.1f} GiB; compute units {d.max_compute_units}; "
                f"unified memory {bool(d.host_unified_memory)}"
            )
    if not working:
        print(
            "No OpenCL device can build kernels. On CPUs newer than PoCL's LLVM 14 knows, "
            "`pip install intel-opencl-rt intel-cmplr-lib-rt` gives a working CPU device; "
            f"{runtime._INSTALL_HINT}"
        )
        return 1
    print("2D models (paper model, or the embedded default that replaces it):")
    from coin_cl.diffusion import available_models

    for name, info in available_models().items():
        print(f"  {name}: {'available' if info['available'] else 'not available'} ({info['reason']})")
    request = os.environ.get("COIN_CL_DEVICE")
    try:
        rt = runtime.get_runtime()
    except runtime.NoDeviceError as exc:
        print(f"default device: none ({exc})")
        return 1
    if request:
        reason = f"COIN_CL_DEVICE={request!r}"
    else:
        reason = next(why for _, why, d in working if runtime.device_label(d) == rt.name)
        reason += "; the order is: a GPU, Intel's CPU runtime, PoCL (COIN_CL_DEVICE overrides)"
    print(f"default device: {rt.name} ({reason})")
    return 0
