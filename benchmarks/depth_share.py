"""Benchmark: how much of Adam's second moment Ref-GS's depth terms may hold
(`RefGSConfig.aux_grad_ratio`, `coin_cl.gs.balance`), and what the whole view pays when they hold
all of it.

From a finished run folder (its stages 0 to 1: the scene, the split, the 2D fills), Ref-GS alone
for that run's Ref-GS step count (TE-D off, its schedule over those steps), one row per cap, plus
a plain Scaffold-GS row (every Ref-GS term off) on the same fills. Scored on the test views' eval
renders against the truth: PSNR over the whole view, outside the masks (where nothing was removed:
pure reconstruction) and inside them (m-PSNR); the ghost figure (`benchmarks/ghost.py`,
ring-relative, and its floor outside the mask); Ref-GS's training minutes; the root-mean-square of
Adam's second moment of the opacity MLP's first layer relative to the plain row's (how much smaller
the photometric steps on the shared MLPs were); and the depth terms' mean scale over the run. With
`--norms`, the uncapped row's final model also gets each term's gradient norm over its parameters
relative to the photometric loss's on the same view (the measurement the cap acts on). A crop grid
of the rows' test views (`crop_grid.py`) goes beside the table.

    python benchmarks/depth_share.py RUN --scene SCENE --out DIR [--ratios 0,1,0.3] [--no-plain]
        [--truth CAPTURE/images] [--norms] [--grid docs/img/NAME.jpg]

RUN: a `coin-cl run` folder of SCENE (the default command's); `--truth`: the object-absent photos of
a virtual-object scene for the ghost's reference (`benchmarks/ghost.py`). Rows run one after the
other in DIR/<row> and are reused when their eval exists. Last line JSON: {row: figures}.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, git_commit  # noqa: E402
from ghost import final_model, ghost_of_model, reference_depths  # noqa: E402

from coin_cl import metrics  # noqa: E402
from coin_cl.checkpoint import load_checkpoint  # noqa: E402
from coin_cl.gs.refgs import RefGSConfig  # noqa: E402
from coin_cl.gs.trainer import CKPT_NAME  # noqa: E402
from coin_cl.pipeline.coin import CoInConfig, inpaint  # noqa: E402
from coin_cl.pipeline.runner import share_stages  # noqa: E402
from coin_cl.pipeline.schedule import run_steps  # noqa: E402
from coin_cl.scene import load_scene  # noqa: E402
from coin_cl.scene.io import read_image, view_stem  # noqa: E402

PLAIN = RefGSConfig(adaptive_weights=False, feature_attention=False, depth_loss=False, prune_points=False,
                    bg_depth=False)  # fmt: skip
# The shared MLP whose second moment the table reads (the depth terms reach it through the opacity).
PROBE_PARAM = "mlp_opacity.0.weight"


def refgs_only(base: Path, out: Path, scene: Path, refgs: RefGSConfig) -> Path:
    """Ref-GS alone in `out` from `base`'s stages 0-1 at `base`'s Ref-GS count (TE-D off), eval included."""
    share_stages(base, out, ("0_scene", "0_refine", "1_inpaint"))
    n = run_steps(base)
    cfg = CoInConfig()
    cfg = replace(cfg, refine=replace(cfg.refine, iters=n.get("refine")), iters_refgs=n["refgs"],
                  iters_ted_finetune=0, iters_ted_adversarial=0, refgs=refgs)  # fmt: skip
    inpaint(scene, out, config=cfg)
    return out


def view_psnr(run: Path, scene) -> dict[str, float]:
    """Mean over the test views of PSNR: whole view, outside the mask, inside it (eval renders)."""
    rows = []
    for i in scene.test_idx:
        img = read_image(run / "eval" / "renders" / f"{view_stem(scene.cameras[i].name, i)}.png")
        gt, m = scene.images[i][..., :3], np.asarray(scene.masks[i], bool)
        rows.append(
            (metrics.psnr(img, gt), metrics.masked_psnr(img, gt, ~m), metrics.masked_psnr(img, gt, m))
        )
    a = np.mean(rows, axis=0)
    return {"psnr": float(a[0]), "psnr_outside": float(a[1]), "m_psnr": float(a[2])}


def adam_rms(run: Path) -> float:
    """Root-mean-square of Adam's second moment of `PROBE_PARAM` at the end of the run's Ref-GS."""
    ck = load_checkpoint(run / "2_refgs" / "gs" / CKPT_NAME)
    st = ck["model"]["optimizer"]["optims"][PROBE_PARAM]["state"][0]
    return float(st["exp_avg_sq"].float().mean().sqrt())


def mean_scales(run: Path) -> dict[str, float]:
    """The depth terms' mean scale over the run (`<term>_scale` of the training log's intervals)."""
    train = json.loads((run / "2_refgs" / "gs" / "log.json").read_text())["train"]
    keys = {k for e in train for k in e if k.endswith("_scale") and k != "scale_reg"}
    return {k[: -len("_scale")]: float(np.mean([e[k] for e in train if k in e])) for k in sorted(keys)}


def term_norms(run: Path, scene, views: int = 10) -> dict[str, float]:
    """Each depth term's gradient norm over all parameters relative to the (unweighted) photometric
    loss's on the same view, at `run`'s Ref-GS model, averaged over up to `views` training views (the
    reference depth on the reference view alone)."""
    import torch

    from coin_cl.gs.balance import grad_norm
    from coin_cl.gs.data import Camera, View
    from coin_cl.gs.refgs import refgs_terms
    from coin_cl.gs.targets import composite_targets
    from coin_cl.gs.terms import LossContext, PhotometricLoss
    from coin_cl.pipeline.inpaint2d import read_inpaints
    from coin_cl.pipeline.refgs import read_bg_depths

    st = json.loads((run / "2_refgs" / "stage.json").read_text())
    train = list(scene.train_idx)
    k = train.index(st["reference"]["index"])
    from coin_cl.gs.model_kinds import model_from_state

    model = model_from_state(load_checkpoint(run / "2_refgs" / "gs" / CKPT_NAME)["model"])
    masks = [np.asarray(scene.masks[i], bool) for i in train]
    prior = json.loads((run / "2_refgs" / "depth_prior.json").read_text())
    cfg = RefGSConfig(**st["config"])
    terms = refgs_terms(cfg, k, masks, 1, depth_prior=np.load(run / "2_refgs" / "depth_prior.npy"),
                        depth_is_disparity=prior["is_disparity"],
                        bg_depths=read_bg_depths(run / "2_refgs" / "bg_depths", scene, train))  # fmt: skip
    photo = PhotometricLoss()  # unweighted: the reference's lambda_r would hide the term's size
    inp = read_inpaints(scene, run / "1_inpaint", train)
    params = [p for p in model.optimizer.params.values() if p.requires_grad]
    ratios: dict[str, list[float]] = {}
    for j in sorted({k, *range(0, len(train), max(1, len(train) // views))}):
        i = train[j]
        tgt = composite_targets(inp[i], scene.images[i], masks[j])
        view = View(
            Camera.from_any(scene.cameras[i], name=str(i)), torch.as_tensor(np.ascontiguousarray(tgt))
        )
        out = model.render(view.camera, 10**9, training=True, return_depth=True)
        ctx = LossContext(view=view, index=j, out=out, step=10**9, model=model)
        g = grad_norm(photo(ctx), params)
        for t in terms:
            if t.auxiliary:
                v = t.weight * t(ctx)
                if v.requires_grad:
                    ratios.setdefault(t.name, []).append(grad_norm(v, params) / g)
    return {n: float(np.mean(r)) for n, r in ratios.items()}


def write_grid(path: Path, runs: list[Path], scene, cell: int = 200) -> None:
    """Every other test view whole (the blur outside the masks), then every test view's mask box
    (`crop_grid.grid`), one column per run and the truth; written as JPEG or PNG by suffix."""
    import cv2
    from crop_grid import grid

    whole = []
    for i in list(scene.test_idx)[::2]:
        stem = view_stem(scene.cameras[i].name, i)
        tiles = [read_image(r / "eval" / "renders" / f"{stem}.png") for r in runs]
        tiles.append(np.asarray(scene.images[i], np.float32)[..., :3])
        h, w = tiles[0].shape[:2]
        size = (cell, max(1, round(h * cell / w)))  # the whole view at the cells' width, no padding
        tiles = [np.pad(cv2.resize(t, size, interpolation=cv2.INTER_AREA), ((0, 4), (0, 4), (0, 0)),
                        constant_values=1) for t in tiles]  # fmt: skip
        whole.append(np.concatenate(tiles, axis=1))
    top = (np.clip(np.concatenate(whole, axis=0), 0, 1) * 255).round().astype(np.uint8)
    boxes = grid(runs, cell)
    img = np.concatenate([top, boxes], axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a finished `coin-cl run` folder of --scene")
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--ratios", default="0,1,0.3", help="aux_grad_ratio per row (0: uncapped)")
    ap.add_argument("--no-plain", action="store_true", help="leave out the plain Scaffold-GS row")
    ap.add_argument("--truth", type=Path, help="object-absent photos for the ghost's reference")
    ap.add_argument("--norms", action="store_true", help="gradient norms of the uncapped row's terms")
    ap.add_argument("--grid", type=Path, help="write the rows' crop grid here")
    args = ap.parse_args()
    rows = {f"ratio {r}": replace(RefGSConfig(), aux_grad_ratio=float(r)) for r in args.ratios.split(",")}
    if not args.no_plain:
        rows["plain"] = PLAIN
    scene = load_scene(args.run / "0_scene" / "scene")
    depths = reference_depths(scene, args.out / "ghost_reference", truth=args.truth)
    n = run_steps(args.run)["refgs"]
    print(f"# {cpu_model()}; commit {git_commit()}; base run {args.run} ({n} Ref-GS steps)")
    res: dict[str, dict] = {}
    for name, cfg in rows.items():
        folder = args.out / name.replace(" ", "_")
        if not (folder / "eval" / "manifest.json").is_file():
            refgs_only(args.run, folder, args.scene, cfg)
        stage = json.loads((folder / "2_refgs" / "stage.json").read_text())
        g = ghost_of_model(final_model(folder), scene, depths)
        res[name] = {**view_psnr(folder, scene), "ghost": g["ghost_ring"], "ghost_floor": g["ghost_outside"],
                     "minutes": stage["train_minutes"], "adam_rms": adam_rms(folder),
                     "scales": mean_scales(folder)}  # fmt: skip
        if args.norms and cfg.aux_grad_ratio == 0 and cfg is not PLAIN:
            res[name]["norms"] = term_norms(folder, scene)
        print(name, json.dumps(res[name]), flush=True)
    ref = res.get("plain", {}).get("adam_rms")
    print("| row | PSNR | outside the masks | m-PSNR | ghost | its floor | Ref-GS min | Adam RMS / plain "
          "| scales |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in res.items():
        rel = f"{r['adam_rms'] / ref:.1f}x" if ref else "-"
        sc = ", ".join(f"{k} {v:.2f}" for k, v in r["scales"].items()) or "-"
        print(f"| {name} | {r['psnr']:.2f} | {r['psnr_outside']:.2f} | {r['m_psnr']:.2f} | "
              f"{r['ghost']:.3f} | {r['ghost_floor']:.3f} | {r['minutes']:.1f} | {rel} | {sc} |")  # fmt: skip
    for name, r in res.items():
        if "norms" in r:
            print(f"{name}: gradient norm over the photometric's: " +
                  ", ".join(f"{k} {v:.1f}x" for k, v in r["norms"].items()))  # fmt: skip
    if args.grid:
        write_grid(args.grid, [args.out / n.replace(" ", "_") for n in rows], scene)
        print("grid columns:", ", ".join(rows), "| truth; top: whole views, bottom: the masks' boxes")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
