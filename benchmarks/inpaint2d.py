"""Stage 1 (paper 4.1) benchmark: the 2D inpainters on holes with a known answer, and SD2's cost at
its real size.

Usage: python benchmarks/inpaint2d.py [--data DIR] [--holes 16] [--size 64] [--lama-path FILE]
                                      [--rows TEXT ...]
                                      [--sd2 | --sd2-json FILE] [--grid PNG] [--out DIR]
Holes:
- "scene": `--holes` square holes of `--size` px in the shared SPIn-NeRF scene's object-present views,
  at least `--gap` px from the object (placed as benchmarks/diffusion.py does, fixed seed); the fill
  sees only the view's own pixels (other views show the held-out surface, which a real object hides);
- "test": the object's masks (dilated 2 px) on the scene's 5 object-absent test views: real-size holes
  (about 230 px) with truth; Telea, FSR, the default and the full-synthesis exemplar rows only;
- "room": the demo room's object masks on its object-absent renders (coin_cl.scene.synthetic, exact
  truth), 4 views; the exemplar rows also copy from the other object-present views, as stage 1 does.
Rows: OpenCV Telea and FSR_FAST, the exemplar inpainter (coin_cl.diffusion.exemplar) and its variants,
LaMa when `--lama-path` / COIN_LAMA_PATH names a TorchScript big-lama.pt. Columns per hole set:
m-PSNR, GMSD (bounding box), HF ratio (mean Sobel magnitude, fill over truth: `metrics.hf_ratio`,
what `coin-cl eval` reports), HF energy (the same with squared magnitudes, benchmarks/diffusion.py's
ratio), SWD (Laplacian-pyramid patches on the bounding box, x1000), colour (sliced W1 of Lab colours
in the mask), seconds per hole.
`--sd2`: SD2-inpainting's UNet and VAE at their published sizes with random weights, one unguided and
one guided step (energy gradient through UNet and VAE decoder) at 512x512 on 2 torch threads: seconds
and peak resident memory; alone it takes minutes (`--sd2-json` reuses a saved measurement).
The LAST line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import cpu_model, default_data, git_commit  # noqa: E402

from coin_cl import metrics  # noqa: E402


def measure_sd2(threads: int = 2) -> dict:
    """One unguided and one guided DDIM-step equivalent of SD2-inpainting at 512x512 (random weights)."""
    from coin_cl.diffusion.sd2 import SD2_VAE_CONFIG, build_sd2_random

    torch.set_num_threads(threads)
    unet, vae = build_sd2_random()
    for m in (unet, vae):
        m.requires_grad_(False)
    g = torch.Generator().manual_seed(0)
    z = torch.randn(1, 4, 64, 64, generator=g)
    cond = torch.randn(1, 5, 64, 64, generator=g)
    text = torch.randn(1, 77, 1024, generator=g)
    t = torch.tensor([500])
    target = torch.rand(1, 3, 512, 512, generator=g)
    sf = SD2_VAE_CONFIG["scaling_factor"]
    print("# SD2 step at 512x512: building done, timing the unguided step ...", flush=True)

    def unguided() -> None:
        with torch.no_grad():
            _ = unet(torch.cat([z, cond], 1), t, encoder_hidden_states=text).sample

    def guided() -> None:
        zz = z.clone().requires_grad_(True)
        eps = unet(torch.cat([zz, cond], 1), t, encoder_hidden_states=text).sample
        a = 0.5  # any alpha-bar: the cost does not depend on it
        x0 = (zz - (1 - a) ** 0.5 * eps) / a**0.5
        img = (vae.decode(x0 / sf).sample + 1) / 2
        ((img - target) ** 2).mean().backward()

    t0 = time.perf_counter()
    unguided()
    u = time.perf_counter() - t0
    print(f"# unguided {u:.1f} s; timing the guided step ...", flush=True)
    t0 = time.perf_counter()
    guided()
    gs = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
    n_unet = sum(p.numel() for p in unet.parameters())
    n_vae = sum(p.numel() for p in vae.parameters())
    return {
        "unguided_step_s": round(u, 2),
        "guided_step_s": round(gs, 2),
        "peak_gib": round(peak, 2),
        "threads": threads,
        "unet_params_m": round(n_unet / 1e6, 1),
        "vae_params_m": round(n_vae / 1e6, 1),
    }


def _bench_diffusion():
    """benchmarks/diffusion.py as a module (its name is taken by the `diffusion` package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_diffusion", ROOT / "benchmarks" / "diffusion.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def scene_cases(data: Path, n: int, size: int, gap: int) -> list[dict]:
    bd = _bench_diffusion()
    imgs, masks, names = bd.load_scene(data)
    out = []
    for v, y, x in bd.place_holes(masks, n, size, gap, seed=0):
        hole = np.zeros(imgs[v].shape[:2], bool)
        hole[y : y + size, x : x + size] = True
        out.append({"name": f"{names[v]}@{y},{x}", "truth": imgs[v], "mask": hole, "sources": None})
    return out


def test_view_cases(data: Path) -> list[dict]:
    """The scene's object-absent test views with the object's masks (test_label, dilated by 2 px as
    stage 1's masks are): real-size holes with truth; own pixels only."""
    out = []
    for line in (data / "views.txt").read_text().splitlines():
        f = line.split()
        if line.startswith("#") or len(f) < 5 or f[2] != "test" or f[3] != "yes":
            continue
        im = cv2.imread(str(data / "images_4" / f[1]), cv2.IMREAD_COLOR)
        m = cv2.imread(str(data / f[4]), cv2.IMREAD_UNCHANGED)
        if im is None or m is None:
            raise FileNotFoundError(f"cannot read {data / 'images_4' / f[1]} or {data / f[4]}")
        m = cv2.dilate((m[: im.shape[0]] > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        truth = im[..., ::-1].astype(np.float32) / 255.0
        out.append({"name": f[1], "truth": truth, "mask": m, "sources": None})
    return out


def room_cases(n_views: int = 8) -> list[dict]:
    from coin_cl.scene.synthetic import make_synthetic

    s = make_synthetic(n_views=n_views, width=256, height=192, seed=0, n_points=1000)
    out = []
    for i in range(1, n_views, 2):
        src = [(s.present[j].astype(np.float32), s.masks[j]) for j in range(n_views) if j != i]
        out.append(
            {
                "name": f"room view {i}",
                "truth": s.absent[i].astype(np.float32),
                "mask": s.masks[i],
                "sources": src,
            }
        )
    return out


def methods(lama_path: str | None) -> dict:
    from coin_cl.diffusion.directional import DirectionalConfig
    from coin_cl.diffusion.exemplar import ExemplarConfig, exemplar_inpaint, smooth_fill
    from coin_cl.diffusion.inpaint2d import opencv_inpaint

    def ex(cfg):
        return lambda c: exemplar_inpaint(c["truth"], c["mask"], cfg, seed=0, sources=c["sources"])

    rows = {
        "OpenCV TELEA": lambda c: opencv_inpaint(c["truth"], c["mask"], "telea"),
        "OpenCV FSR_FAST": lambda c: opencv_inpaint(c["truth"], c["mask"], "fsr_fast"),
        "harmonic (Laplace)": lambda c: smooth_fill(c["truth"], c["mask"], "harmonic"),
        "embedded (exemplar, default)": ex(ExemplarConfig()),
        "exemplar, FSR structure": ex(ExemplarConfig(structure="fsr_fast")),
        "exemplar, FSR surfaces structure": ex(ExemplarConfig(structure="fsr_surfaces")),
        "exemplar + grain": ex(ExemplarConfig(grain=DirectionalConfig())),
        "exemplar + grain on harmonic": ex(
            ExemplarConfig(grain=DirectionalConfig(), grain_structure="harmonic")
        ),
        "exemplar, harmonic structure": ex(ExemplarConfig(structure="harmonic")),
        "exemplar full synthesis": ex(ExemplarConfig(mode="full")),
        "exemplar hf, gain 1.0": ex(ExemplarConfig(mode="hf", hf_gain=1.0)),
        "exemplar hf, gain 1.2": ex(ExemplarConfig(mode="hf", hf_gain=1.2)),
        "exemplar full, patch 9": ex(ExemplarConfig(mode="full", patch=9)),
        "exemplar mean vote (default before)": ex(ExemplarConfig(vote="mean")),
        "exemplar sigma 3, texture match 2": ex(ExemplarConfig(hf_sigma=3.0, texture_gain_max=2.0)),
    }
    if lama_path:
        from coin_cl.diffusion.inpaint2d import paste
        from coin_cl.diffusion.lama import lama_inpaint, load_lama

        model = load_lama(lama_path)
        rows["LaMa (TorchScript)"] = lambda c: paste(
            c["truth"], lama_inpaint(model, c["truth"], c["mask"]), c["mask"], 2
        )
    return rows


def evaluate(fn, cases: list[dict]) -> tuple[dict, list[np.ndarray]]:
    acc: dict[str, list[float]] = {k: [] for k in ("mpsnr", "gmsd", "hf", "hf2", "swd", "color")}
    outs = []
    t0 = time.perf_counter()
    for c in cases:
        inp = c["truth"].copy()
        inp[c["mask"]] = 0.5  # the fill must not see the truth inside the hole
        out = fn({**c, "truth": inp})
        t, m = c["truth"], c["mask"]
        acc["mpsnr"].append(metrics.masked_psnr(out, t, m))
        acc["gmsd"].append(metrics.bbox_gmsd(out, t, m))
        acc["hf"].append(metrics.hf_ratio(out, t, m))
        acc["hf2"].append(metrics.hf_ratio(out, t, m, power=2))
        acc["swd"].append(metrics.swd(out, t, m))
        acc["color"].append(metrics.color_distance(out, t, m))
        outs.append(out)
    r = {k: float(np.nanmean(v)) for k, v in acc.items()}
    r["s"] = (time.perf_counter() - t0) / len(cases)
    return r, outs


def fmt(r: dict) -> dict:
    return {
        "mPSNR dB": f"{r['mpsnr']:.2f}",
        "GMSD": f"{r['gmsd']:.4f}",
        "HF ratio": f"{r['hf']:.3f}",
        "HF energy": f"{r['hf2']:.3f}",
        "SWD": f"{r['swd']:.0f}",
        "colour": f"{r['color']:.2f}",
        "s per hole": f"{r['s']:.2f}",
    }


def table(rows: list[dict], cols: list[str]) -> str:
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    out += ["| " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(out)


def crop_grid(
    cases: list[dict], outs: dict[str, list[np.ndarray]], pick: list[int], cell: int = 96
) -> np.ndarray:
    """Rows = cases, columns = each method's crop of the hole's bounding box (+8 px), then the truth."""
    rows = []
    for k in pick:
        c = cases[k]
        crop = metrics.bbox_crop(c["mask"], pad=8)
        tiles = [outs[name][k][crop] for name in outs] + [c["truth"][crop]]
        h, w = tiles[0].shape[:2]
        sc = cell / max(h, w)
        size = (max(1, round(w * sc)), max(1, round(h * sc)))
        tiles = [cv2.resize(t, size, interpolation=cv2.INTER_NEAREST) for t in tiles]
        tiles = [
            np.pad(t, ((0, cell + 4 - t.shape[0]), (0, cell + 4 - t.shape[1]), (0, 0)), constant_values=1)
            for t in tiles
        ]
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--holes", type=int, default=16)
    ap.add_argument("--size", type=int, default=64, help="held-out hole side in pixels")
    ap.add_argument("--gap", type=int, default=40, help="minimum distance of a hole from the object")
    ap.add_argument("--lama-path", default=os.environ.get("COIN_LAMA_PATH"))
    ap.add_argument("--sd2", action="store_true", help="measure SD2 at its real size (minutes)")
    ap.add_argument("--sd2-only", action="store_true", help="only the SD2 measurement")
    ap.add_argument("--sd2-json", type=Path, default=None, help="a saved --sd2 measurement to report")
    ap.add_argument("--grid", type=Path, default=ROOT / "docs" / "img" / "inpaint2d_grid.png")
    ap.add_argument(
        "--rows",
        nargs="+",
        default=None,
        metavar="TEXT",
        help="run only the rows whose name contains one of these (default: every row)",
    )
    args = ap.parse_args()
    torch.set_num_threads(2)
    head = f"{cpu_model()}; {os.cpu_count()} cores; torch {torch.__version__}; commit {git_commit()}"
    if args.sd2_only:
        print(f"# SD2 cost: {head}", flush=True)
        print(json.dumps(measure_sd2()))
        return
    print(f"# coin-cl stage-1 inpainting benchmark: {head}; {time.strftime('%Y-%m-%d %H:%M')}", flush=True)
    data = args.data or default_data()
    if not (data / "images_4").is_dir():
        raise SystemExit(f"SPIn-NeRF scene not found at {data}: pass --data or set COIN_DATA")
    sets = {
        "scene": scene_cases(data, args.holes, args.size, args.gap),
        "room": room_cases(),
        "test": test_view_cases(data),
    }
    results: dict[str, dict[str, dict]] = {k: {} for k in sets}
    outs: dict[str, dict[str, list]] = {k: {} for k in sets}
    big = ("OpenCV TELEA", "OpenCV FSR_FAST", "harmonic (Laplace)", "embedded (exemplar, default)",
           "exemplar, FSR structure", "exemplar, harmonic structure", "exemplar full synthesis",
           "exemplar mean vote (default before)", "exemplar + grain",
           "exemplar + grain on harmonic")  # fmt: skip
    rows = methods(args.lama_path)
    if args.rows:
        rows = {n: fn for n, fn in rows.items() if any(t in n for t in args.rows)}
        if not {"embedded (exemplar, default)", "OpenCV TELEA", "OpenCV FSR_FAST"} <= set(rows):
            raise SystemExit(
                "--rows must keep 'embedded (exemplar, default)' and both OpenCV rows: "
                "the summary compares against them"
            )
    for name, fn in rows.items():
        for k, cases in sets.items():
            if k == "test" and name not in big and not name.startswith("LaMa"):
                continue  # real-size holes take ~30 s each: the main rows only
            results[k][name], outs[k][name] = evaluate(fn, cases)
        print(f"# {name}: done", flush=True)
    cols = ["method", "mPSNR dB", "GMSD", "HF ratio", "HF energy", "SWD", "colour", "s per hole"]
    print(
        f"\n## {args.holes} held-out {args.size}px holes of {data.name} (>= {args.gap}px from the object)\n"
    )
    print(table([{"method": n, **fmt(r)} for n, r in results["scene"].items()], cols))
    print(f"\n## Demo room: object masks on {len(sets['room'])} object-absent renders (exact truth)\n")
    print(table([{"method": n, **fmt(r)} for n, r in results["room"].items()], cols))
    print(f"\n## The object's masks on the {len(sets['test'])} object-absent test views of {data.name}\n")
    print(table([{"method": n, **fmt(r)} for n, r in results["test"].items()], cols))
    grid = np.concatenate(
        [
            crop_grid(sets["scene"], outs["scene"], [0, 4, 8, 12]),
            crop_grid(sets["room"], outs["room"], [0, 1]),
        ],
        axis=0,
    )
    args.grid.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.grid), (np.clip(grid, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))
    print(f"\ncrop grid (columns: {', '.join(outs['scene'])}, truth): {args.grid}")
    tgrid = crop_grid(sets["test"], outs["test"], list(range(len(sets["test"]))), cell=160)
    tpath = args.grid.with_name(args.grid.stem + "_testviews.png")
    cv2.imwrite(str(tpath), (np.clip(tgrid, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))
    print(f"test-view crop grid (columns: {', '.join(outs['test'])}, truth): {tpath}")
    sd2 = {"unguided_step_s": None, "guided_step_s": None, "peak_gib": None}
    if args.sd2_json:
        sd2 = json.loads(args.sd2_json.read_text().strip().splitlines()[-1])
    elif args.sd2:
        sd2 = measure_sd2()
    if sd2["guided_step_s"] is not None:
        from coin_cl.diffusion.sd2 import sd2_run_estimate

        print("\n## SD2-inpainting at 512x512, published sizes, random weights, 2 threads\n")
        print(
            table(
                [
                    {"step": "unguided", "s": sd2["unguided_step_s"]},
                    {"step": "guided", "s": sd2["guided_step_s"]},
                ],
                ["step", "s"],
            )
        )
        print(
            f"\npeak resident memory {sd2['peak_gib']} GiB; "
            + sd2_run_estimate(34, 50, measured=sd2)["message"]
        )
    sc, em = results["scene"], results["scene"]["embedded (exemplar, default)"]
    tel, fsr = sc["OpenCV TELEA"], sc["OpenCV FSR_FAST"]
    res = {
        "telea_mpsnr": round(tel["mpsnr"], 3),
        "telea_gmsd": round(tel["gmsd"], 4),
        "telea_swd": round(tel["swd"], 1),
        "fsr_gmsd": round(fsr["gmsd"], 4),
        "fsr_swd": round(fsr["swd"], 1),
        "embedded_mpsnr": round(em["mpsnr"], 3),
        "embedded_gmsd": round(em["gmsd"], 4),
        "embedded_hf_ratio": round(em["hf"], 3),
        "embedded_hf_energy_ratio": round(em["hf2"], 3),
        "embedded_swd": round(em["swd"], 1),
        "embedded_color": round(em["color"], 3),
        "telea_color": round(tel["color"], 3),
        "embedded_train_s": 0.0,  # nothing is trained: patches are copied at fill time (s per hole below)
        "embedded_s_per_hole": round(em["s"], 2),
        "room_telea_mpsnr": round(results["room"]["OpenCV TELEA"]["mpsnr"], 3),
        "room_embedded_mpsnr": round(results["room"]["embedded (exemplar, default)"]["mpsnr"], 3),
        "room_telea_swd": round(results["room"]["OpenCV TELEA"]["swd"], 1),
        "room_embedded_swd": round(results["room"]["embedded (exemplar, default)"]["swd"], 1),
        "testviews_telea_mpsnr": round(results["test"]["OpenCV TELEA"]["mpsnr"], 3),
        "testviews_embedded_mpsnr": round(results["test"]["embedded (exemplar, default)"]["mpsnr"], 3),
        "testviews_telea_swd": round(results["test"]["OpenCV TELEA"]["swd"], 1),
        "testviews_embedded_swd": round(results["test"]["embedded (exemplar, default)"]["swd"], 1),
        "sd2_unguided_step_s": sd2["unguided_step_s"],
        "sd2_guided_step_s": sd2["guided_step_s"],
        "sd2_peak_gib": sd2["peak_gib"],
        "floors_ok": bool(
            em["gmsd"] < min(tel["gmsd"], fsr["gmsd"])
            and em["swd"] < min(tel["swd"], fsr["swd"])
            and 0.8 <= em["hf"] <= 1.25
            and em["mpsnr"] >= tel["mpsnr"] - 1.5
        ),
        "cpu": cpu_model(),
        "commit": git_commit(),
    }
    print(json.dumps(res))


if __name__ == "__main__":
    main()
