"""`coin-cl demo` and `coin-cl doctor`: the engine's own subcommands."""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

from coin_cl.demo import DEMO_BUDGET_MINUTES


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the engine and CoIn on embedded scenes (no data or download needed)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("demo_out"),
        help="output folder: new, empty, or one coin-cl demo made",
    )
    p.add_argument("--frames", type=int, default=12, help="turntable frames")
    p.add_argument("--size", type=int, nargs=2, default=(480, 320), metavar=("W", "H"))
    p.add_argument("--budget", type=float, default=DEMO_BUDGET_MINUTES,
                   help="CoIn's wall-clock minutes on the synthetic room, every stage included (the demo "
                   "adds both baselines at CoIn's GS steps)")  # fmt: skip
    p.add_argument("--room-size", type=int, nargs=2, default=(192, 144), metavar=("W", "H"))
    p.add_argument("--room-views", type=int, default=24, help="synthetic room views (1 in 4 for testing)")
    p.add_argument(
        "--iters", type=int, default=None, help="steps of each CoIn training stage (overrides --budget)"
    )
    p.add_argument("--prior-seconds", type=float, default=None, help="scene prior training (smoke runs)")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="steps of the masked-reconstruction baseline (default: CoIn's GS steps, stopped at --budget "
        "minutes of training)",
    )
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


def run_demo(args: argparse.Namespace) -> int:
    """`coin-cl demo`: `coin_cl.demo.run_demo` with the command's options."""
    from coin_cl.cli.guard import output_folder
    from coin_cl.demo import run_demo as demo

    out = Path(args.out)
    with output_folder(out, "demo"):
        summary = demo(
            out, args.frames, tuple(args.size), args.steps, args.render_only, args.device,
            budget=args.budget, room_size=tuple(args.room_size), iters=args.iters,
            room_views=args.room_views, prior_seconds=args.prior_seconds,
        )  # fmt: skip
    if "room" in summary:
        print((out / "room" / "results.md").read_text())
        print(f"CoIn's run on the room, to open: {out / 'room' / 'coin' / 'report.html'}")
    print(f"wrote {out}/ (turntable/, room/, demo.json)")
    return 0


def run_doctor(args: argparse.Namespace) -> int:
    """Print versions and, for every OpenCL device, whether it builds and runs kernels; exit 1 when
    none does (with what to install)."""
    from importlib import metadata

    from coin_cl.engine import devices
    from coin_cl.engine.errors import NoDeviceError
    from coin_cl.engine.runtime import get_runtime

    if args.working:
        labels = [devices.device_label(d) for d in devices.working_devices()]
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
    from coin_cl.opencv_contrib import FIX, missing_contrib

    missing = missing_contrib()
    if missing:
        print(
            f"  cv2 lacks the contrib modules {', '.join(missing)} (a plain OpenCV wheel shadows it): {FIX}"
        )
    print(f"OCL_ICD_VENDORS={os.environ.get('OCL_ICD_VENDORS', '(unset)')}")
    visible = [d for _, d in devices.all_devices()]
    if not visible:
        print(f"OpenCL: no platform found; {devices.INSTALL_HINT}")
        return 1
    print("OpenCL devices (probe = build and run a tiny kernel):")
    working = []
    for d in visible:
        probe = devices.probe_device(d)
        rank, why = devices.default_rank(d)
        state = f"works ({probe.seconds:.2f} s to build and run)" if probe.ok else f"FAILS: {probe.message}"
        print(f"  {devices.device_label(d)}  [{d.version}]")
        print(f"    probe: {state}")
        if probe.ok:
            working.append((rank, why, d))
            print(
                f"    float atomics: {devices.probe_float_atomics(d)}; "
                f"fp64: {'cl_khr_fp64' in d.extensions}; "
                f"global memory {d.global_mem_size / 2**30:.1f} GiB; compute units {d.max_compute_units}; "
                f"unified memory {bool(d.host_unified_memory)}"
            )
    if not working:
        print(f"No OpenCL device can build kernels. {devices.NO_BUILD_HINT}")
        return 1
    print("2D models (paper model, or the embedded default that replaces it):")
    from coin_cl.diffusion import available_models

    for name, info in available_models().items():
        print(f"  {name}: {'available' if info['available'] else 'not available'} ({info['reason']})")
    request = os.environ.get("COIN_CL_DEVICE")
    try:
        rt = get_runtime()
    except NoDeviceError as exc:
        print(f"default device: none ({exc})")
        return 1
    if request:
        reason = f"COIN_CL_DEVICE={request!r}"
    else:
        reason = next(why for _, why, d in working if devices.device_label(d) == rt.name)
        reason += "; the order is: a GPU, Intel's CPU runtime, PoCL (COIN_CL_DEVICE overrides)"
    print(f"default device: {rt.name} ({reason})")
    return 0
