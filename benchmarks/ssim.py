"""SSIM benchmark: the fused OpenCL op (kernels/ssim.cl) against torch's convolutions,
run time next to error against the float64 twin, at several image sizes and windows.

    python benchmarks/ssim.py [--runs 15]

Images: a random texture and a blurred, noised copy (SSIM around 0.3-0.6, like a training render
against its target), [1, H, W, 3]. Times are medians of --runs after a warm-up, forward and
forward + backward (the gradient to the first image, as in training). Errors: max |S - S64| of the
SSIM map, and max |g - g64| / max |g64| of its gradient for a random cotangent, both against
`coin_cl.engine.reference.ssim_map` in float64. The last line printed is one JSON object.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402

import torch  # noqa: E402
from common import cpu_model, git_commit, median_time  # noqa: E402

from coin_cl.engine import ops, reference  # noqa: E402
from coin_cl.engine.runtime import get_runtime  # noqa: E402

SIZES = [(128, 96), (504, 284), (1008, 567)]
WINDOWS = [(11, 1.5), (7, 1.0)]


def images(w: int, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, h, w, 3, generator=g, dtype=torch.float64)
    b = (torch.nn.functional.avg_pool2d(a.permute(0, 3, 1, 2), 3, 1, 1).permute(0, 2, 3, 1)
         + 0.05 * torch.randn(1, h, w, 3, generator=g, dtype=torch.float64)).clamp(0, 1)  # fmt: skip
    return a, b


def ssim(impl: str, x: torch.Tensor, b: torch.Tensor, rt, **kw) -> torch.Tensor:
    if impl == "opencl":
        return ops.ssim_map(x, b, device=rt, **kw)
    return reference.ssim_map(x, b, **kw)


def row(impl: str, a: torch.Tensor, b: torch.Tensor, v: torch.Tensor, rt, runs: int, **kw) -> tuple:
    """(forward s, forward + backward s) medians for one implementation on float32 inputs."""

    def fwd():
        with torch.no_grad():
            ssim(impl, a, b, rt, **kw)

    def fwd_bwd():
        x = a.clone().requires_grad_()
        torch.autograd.grad(ssim(impl, x, b, rt, **kw), x, v)

    return median_time(fwd, runs), median_time(fwd_bwd, runs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=15)
    args = ap.parse_args()
    rt = get_runtime()
    print(f"# coin-cl SSIM benchmark: {cpu_model()}; {os.cpu_count()} cores; OpenCL {rt.name}; torch "
          f"{torch.__version__} ({torch.get_num_threads()} threads); commit {git_commit()}")  # fmt: skip
    print("\n| size | window | impl | fwd ms | fwd+bwd ms | max abs err S | max rel err grad |")
    print("|---|---|---|---|---|---|---|")
    result: dict = {}
    for w, h in SIZES:
        a64, b64 = images(w, h)
        v64 = torch.randn(1, h, w, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        for win, sigma in WINDOWS:
            kw = dict(window=win, sigma=sigma)
            x64 = a64.clone().requires_grad_()
            s64 = reference.ssim_map(x64, b64, **kw)
            (g64,) = torch.autograd.grad(s64, x64, v64)
            a32, b32, v32 = a64.float(), b64.float(), v64.float()
            for impl in ("opencl", "torch"):
                x = a32.clone().requires_grad_()
                s = ssim(impl, x, b32, rt, **kw)
                (g,) = torch.autograd.grad(s, x, v32)
                err_s = float((s.double() - s64).abs().max())
                err_g = float((g.double() - g64).abs().max() / g64.abs().max())
                t_f, t_fb = row(impl, a32, b32, v32, rt, args.runs, **kw)
                name = "opencl" if impl == "opencl" else "torch float32"
                print(f"| {w}x{h} | {win} (sigma {sigma}) | {name} | {t_f * 1e3:.2f} | {t_fb * 1e3:.2f} | "
                      f"{err_s:.2e} | {err_g:.2e} |")  # fmt: skip
                result[f"{impl}_{w}x{h}_w{win}"] = {"fwd_s": t_f, "fwd_bwd_s": t_fb, "err_ssim": err_s,
                                                   "err_grad": err_g}  # fmt: skip
    result.update(cpu=cpu_model(), device=rt.name, commit=git_commit())
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
