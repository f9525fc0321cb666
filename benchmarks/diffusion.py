"""diffusion/ benchmark: sampler error against run time, the scene prior against its training time
beside OpenCV, and per-step times for budgeting the stages.

Usage: python benchmarks/diffusion.py [--quick] [--data DIR] [--minutes 1 2 5 10] [--holes 8]
  --quick trains the scene prior for 1 and 2 minutes only.
Tables:
1. Analytic Gaussian model (exact denoiser, 4-D): error of the sampled std (exact, no Monte Carlo: the
   DDIM map is affine) against steps, 'uniform' and 'quad', with the run time for 1000 samples.
2. Scene prior on held-out square holes of the shared SPIn-NeRF scene (placed at random, with a fixed
   seed, at least `--gap` px away from the object masks and excluded from training), against its
   training minutes, beside OpenCV TELEA and FSR_FAST on the same holes: masked PSNR (hole pixels),
   GMSD on the hole's bounding box (cv2.quality), and the high-frequency ratio (mean squared Sobel
   gradient of the luminance in the hole, fill over truth; 1 = as much texture as the truth).
3. Per-step time of each model at its working size, unguided and guided (backprop through the
   denoiser and the decoder), and of the feature extractors at 256x256.
The LAST line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from coin_cl.diffusion.analytic import GaussianDenoiser  # noqa: E402
from coin_cl.diffusion.features import AnalyticFeatures, DinoFeatures, DinoViT  # noqa: E402
from coin_cl.diffusion.inpaint2d import InpaintConfig, inpaint_image, opencv_inpaint  # noqa: E402
from coin_cl.diffusion.sampling import DDIMSampler, SamplerConfig  # noqa: E402
from coin_cl.diffusion.scene_prior import PriorCondition, ScenePriorConfig, train_scene_prior  # noqa: E402
from common import cpu_model, default_data, git_commit, median_time  # noqa: E402

from coin_cl import metrics  # noqa: E402


def table(rows: list[dict], cols: list[str]) -> str:
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        out.append("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------------


def bench_analytic() -> list[dict]:
    mu = torch.tensor([1.0, -0.5, 0.3, 2.0], dtype=torch.float64)
    sd = torch.tensor([0.5, 1.0, 1.5, 0.8], dtype=torch.float64)
    rows = []
    for disc in ("uniform", "quad"):
        for steps in (5, 10, 20, 50, 100, 200):
            den = GaussianDenoiser(mu, sd)
            s = DDIMSampler(den, SamplerConfig(num_steps=steps, discretization=disc))
            m, st = den.sample_moments(s)
            m0, s0 = den.marginal(int(s.timesteps[-1]))
            g = torch.Generator().manual_seed(0)
            z = m0 + s0 * torch.randn(1000, 4, generator=g, dtype=torch.float64)
            t0 = time.perf_counter()
            s.sample(z)
            dt = time.perf_counter() - t0
            rows.append(
                {
                    "discretization": disc,
                    "steps": steps,
                    "max abs err std": f"{float((st - sd).abs().max()):.2e}",
                    "max abs err mean": f"{float((m - mu).abs().max()):.1e}",
                    "time 1000 samples s": f"{dt:.4f}",
                }
            )
    return rows


def load_scene(data: Path) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """The 34 object-present training views (float RGB [0, 1]) and their object masks."""
    label = data / "images_4" / "label"
    names = sorted(p.name for p in label.glob("*.png"))
    imgs, masks = [], []
    for n in names:
        im = cv2.imread(str(data / "images_4" / n), cv2.IMREAD_COLOR)
        m = cv2.imread(str(label / n), cv2.IMREAD_UNCHANGED)
        if im is None or m is None:
            raise FileNotFoundError(f"cannot read {data / 'images_4' / n} or its mask")
        imgs.append(im[..., ::-1].astype(np.float32) / 255.0)
        masks.append(m > 0)
    return imgs, masks, names


def place_holes(
    masks: list[np.ndarray], n: int, size: int, gap: int, seed: int
) -> list[tuple[int, int, int]]:
    """n holes (view, y, x), one per view (views spread over the set), at least gap px from objects."""
    rng = np.random.default_rng(seed)
    views = np.linspace(0, len(masks) - 1, n).round().astype(int)
    out = []
    for v in views:
        H, W = masks[v].shape
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1))
        near = cv2.dilate(masks[v].astype(np.uint8), k) > 0
        for _ in range(1000):
            y, x = int(rng.integers(0, H - size)), int(rng.integers(0, W - size))
            if not near[y : y + size, x : x + size].any():
                out.append((int(v), y, x))
                break
        else:
            raise RuntimeError(f"no room for a {size}px hole in view {v}")
    return out


def gmsd(ref: np.ndarray, img: np.ndarray) -> float:
    return metrics.gmsd(img, ref)


def hf_energy_ratio(img: np.ndarray, truth: np.ndarray, m: np.ndarray) -> float:
    """Gradient energy in the hole, fill over truth (`metrics.hf_ratio` at power 2)."""
    return metrics.hf_ratio(img, truth, m, power=2)


def score(truth: np.ndarray, out: np.ndarray, hole: np.ndarray, box: tuple[slice, slice]) -> dict:
    mse = float(((out - truth)[hole] ** 2).mean())
    return {
        "mpsnr": -10 * np.log10(max(mse, 1e-12)),
        "gmsd": gmsd(truth[box], out[box]),
        "hf": hf_energy_ratio(out, truth, hole),
    }


def evaluate(method, imgs, holes, size) -> tuple[dict, float]:
    acc = {"mpsnr": [], "gmsd": [], "hf": []}
    t0 = time.perf_counter()
    for v, y, x in holes:
        hole = np.zeros(imgs[v].shape[:2], bool)
        hole[y : y + size, x : x + size] = True
        out = method(imgs[v], hole)
        for k, val in score(imgs[v], out, hole, (slice(y, y + size), slice(x, x + size))).items():
            acc[k].append(val)
    return {k: float(np.mean(v)) for k, v in acc.items()}, (time.perf_counter() - t0) / len(holes)


def bench_prior(
    data: Path, minutes: list[float], n_holes: int, size: int, gap: int
) -> tuple[list[dict], dict]:
    imgs, masks, _ = load_scene(data)
    holes = place_holes(masks, n_holes, size, gap, seed=0)
    exclude = [m.copy() for m in masks]
    for v, y, x in holes:  # held out: never a training target nor context with a loss
        exclude[v][max(y - 8, 0) : y + size + 8, max(x - 8, 0) : x + size + 8] = True
    rows, last = [], {}
    for name, meth in (("OpenCV TELEA", "telea"), ("OpenCV FSR_FAST", "fsr_fast")):
        r, dt = evaluate(lambda im, h, m=meth: opencv_inpaint(im, h, m), imgs, holes, size)
        rows.append(
            {"method": name, "train min": "-", "train steps": "-", **fmt(r), "s per hole": f"{dt:.2f}"}
        )
        last[meth] = r
    for mins in minutes:
        cfg = ScenePriorConfig(train_seconds=60.0 * mins)
        prior = train_scene_prior(imgs, exclude, cfg, cache_dir=None, progress=False)
        icfg = InpaintConfig(sampler_prior=SamplerConfig(num_steps=50, eta=0.0))

        def fill(im, h, p=prior, c=icfg):
            return inpaint_image(im, h, scene_prior=p, cfg=c, seed=0)[0]

        r, dt = evaluate(fill, imgs, holes, size)
        rows.append(
            {
                "method": "scene prior (50 DDIM steps)",
                "train min": mins,
                "train steps": prior.info["steps"],
                **fmt(r),
                "s per hole": f"{dt:.2f}",
            }
        )
        last["prior"] = r
        last["prior_train_s"] = prior.info["train_s"]
        last["prior_obj"] = prior
    return rows, last


def fmt(r: dict) -> dict:
    return {"mPSNR dB": f"{r['mpsnr']:.2f}", "GMSD": f"{r['gmsd']:.4f}", "HF ratio": f"{r['hf']:.3f}"}


def bench_steps(prior) -> tuple[list[dict], dict]:
    rows = []
    P = prior.work_size
    img = torch.rand(1, 3, P, P, generator=torch.Generator().manual_seed(0))
    hole = torch.zeros(1, 1, P, P)
    hole[..., P // 4 : 3 * P // 4, P // 4 : 3 * P // 4] = 1
    cond = prior.make_condition(img, hole)
    assert isinstance(cond, PriorCondition)
    feats = AnalyticFeatures()
    ref_f = feats(img)

    def energy(x):  # the CLG energy's form: 1 - cos(features) + L2(RGB)
        return (1 - F.cosine_similarity(feats(x), ref_f, dim=1)).mean() + ((x - img) ** 2).mean()

    s = DDIMSampler(prior, SamplerConfig(num_steps=50, guidance_scale=0.3))
    z = torch.randn(1, 3, P, P)
    unguided = median_time(lambda: s.step(z, 25, cond), 5)
    guided = median_time(lambda: s.step(z, 25, cond, energy=energy), 5)
    rows.append(
        {
            "model": f"scene prior {P}x{P}",
            "unguided step s": f"{unguided:.4f}",
            "guided step s": f"{guided:.4f}",
        }
    )
    rows.append(
        {
            "model": "Stable Diffusion 2 inpainting 512x512",
            "unguided step s": "not run (no weights)",
            "guided step s": "not run (no weights)",
        }
    )
    x = torch.rand(1, 3, 256, 256, requires_grad=True)

    def fb(ext):
        def f():
            ext(x).square().mean().backward()

        return f

    a_fwd = median_time(lambda: feats(x.detach()), 5)
    a_fb = median_time(fb(feats), 5)
    rows.append(
        {
            "model": "analytic features 256x256 (fwd / fwd+bwd)",
            "unguided step s": f"{a_fwd:.4f}",
            "guided step s": f"{a_fb:.4f}",
        }
    )
    dino = DinoFeatures(DinoViT().eval().requires_grad_(False))  # random weights: the timing is the same
    d_fwd = median_time(lambda: dino(x.detach()), 3)
    d_fb = median_time(fb(dino), 3)
    rows.append(
        {
            "model": "DINO ViT-S/16 + JBU 256x256, random weights (fwd / fwd+bwd)",
            "unguided step s": f"{d_fwd:.4f}",
            "guided step s": f"{d_fb:.4f}",
        }
    )
    return rows, {"unguided": unguided, "guided": guided}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="train the scene prior for 1 and 2 minutes only")
    ap.add_argument("--minutes", type=float, nargs="+", default=[1, 2, 5, 10])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--holes", type=int, default=8)
    ap.add_argument("--size", type=int, default=64, help="held-out hole side in pixels")
    ap.add_argument("--gap", type=int, default=40, help="minimum distance of a hole from the object")
    args = ap.parse_args()
    minutes = [1, 2] if args.quick else args.minutes
    torch.set_num_threads(max(1, min(os.cpu_count() or 1, 2)))
    data = args.data or default_data()
    print(
        f"# coin-cl diffusion benchmark: {cpu_model()}; {os.cpu_count()} cores; torch {torch.__version__}; "
        f"commit {git_commit()}; {time.strftime('%Y-%m-%d %H:%M')}"
    )
    print("\n## Analytic Gaussian model: error against steps (exact moments)\n")
    print(
        table(
            bench_analytic(),
            ["discretization", "steps", "max abs err std", "max abs err mean", "time 1000 samples s"],
        )
    )
    if not (data / "images_4").is_dir():
        raise SystemExit(f"SPIn-NeRF scene not found at {data}: pass --data or set COIN_DATA")
    print(
        f"\n## Scene prior on {args.holes} held-out {args.size}px holes of {data.name} "
        f"(>= {args.gap}px from the object), training minutes {minutes}\n"
    )
    rows, last = bench_prior(data, minutes, args.holes, args.size, args.gap)
    print(table(rows, ["method", "train min", "train steps", "mPSNR dB", "GMSD", "HF ratio", "s per hole"]))
    print("\n## Per-step time at the working size (guided = energy gradient through denoiser and decoder)\n")
    srows, st = bench_steps(last["prior_obj"])
    print(table(srows, ["model", "unguided step s", "guided step s"]))
    res = {
        "prior_mpsnr": round(last["prior"]["mpsnr"], 3),
        "telea_mpsnr": round(last["telea"]["mpsnr"], 3),
        "fsr_mpsnr": round(last["fsr_fast"]["mpsnr"], 3),
        "prior_gmsd": round(last["prior"]["gmsd"], 4),
        "telea_gmsd": round(last["telea"]["gmsd"], 4),
        "fsr_gmsd": round(last["fsr_fast"]["gmsd"], 4),
        "prior_hf_ratio": round(last["prior"]["hf"], 3),
        "telea_hf_ratio": round(last["telea"]["hf"], 3),
        "fsr_hf_ratio": round(last["fsr_fast"]["hf"], 3),
        "prior_train_s": round(last["prior_train_s"], 1),
        "guided_step_s": round(st["guided"], 4),
        "unguided_step_s": round(st["unguided"], 4),
        "cpu": cpu_model(),
        "torch": torch.__version__,
        "minutes": minutes,
    }
    print(json.dumps(res))


if __name__ == "__main__":
    main()
