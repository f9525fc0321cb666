"""Benchmark: removal on real captures. CoIn's default command beside the naive baseline, masked
reconstruction, a smooth stage 1 and (SPIn-NeRF, whose default takes the dataset's LaMa fills) the embedded
inpainter as stage 1, scored on each scene's
object-absent test views.

Scenes (`--scenes`; folders under `--data`, default `$COIN_DATA` else `../shared/data`):
    spinnerf   spinnerf_scene1: the 5 object-absent ground-truth views are the test views
    cup_plain  a virtual box on plain wood, made from cup_capture by `coin-cl make-scene
               --from-capture` with docs/VIRTUAL_OBJECTS.md's placement (built under OUT/scenes/ on
               first use, through `coin_cl.prepare.virtual_scene.make_virtual_scene`; reused after)
    cup_edge   the same at the desk's back edge

Rows (`--rows`; each a run folder OUT/<scene>/<row>):
    default       exactly `coin-cl run SCENE --out DIR` (with `--budget B` when --budget is given)
    naive         the paper's naive method: the default row's stage-1 inpainter over each whole
                  input mask (`inpaint_region="input"`, no observed/unseen split), then plain
                  Scaffold-GS for as many GS steps as the default row trained
                  (`coin_cl.demo.baseline_config`, stage 0 shared)
    masked_recon  3DGS with the object's pixels left out of the loss, the same GS steps
                  (`coin_cl.demo.room_baseline` on the default row's working-resolution scene)
    smooth        the default pipeline at the default row's steps (`coin.steps_from`; TE-D's
                  adversarial steps as fine-tune steps, as `coin-cl run` plans a run with such fills)
                  with OpenCV's Telea fill alone as stage 1
                  (`Inpaint2DConfig(inpainter="telea", use_dataset=False)`)
    embedded      (spinnerf only) the default pipeline at the default row's steps (as smooth's) with
                  the embedded exemplar inpainter as stage 1 (`Inpaint2DConfig(use_dataset=False)`):
                  `coin-cl run` takes the dataset's LaMa inpaints on SPIn-NeRF (use_dataset is on by
                  default), so there the default row is CoIn with LaMa and this row is what a user
                  without precomputed fills gets; on the cup scenes the default row is already that.
                  The "stage 1" column names the sources each row really used

Columns: PSNR, m-PSNR, VGG-PD (whole view), m-VGG-PD (mask's bounding box), bbox GMSD, HF ratio
(`coin_cl.evaluation`), the ghost figure (`benchmarks/ghost.py`: the share of the test masks rendered
more than 10 % in front of a Scaffold-GS fitted to the object-absent photos, the test views or on a
cup scene every view's, `--ghost-iters` steps at least, cached in OUT/<scene>/ghost_reference) and
its ring-relative form (the reference scaled to the render around the mask first), minutes (what
the row's stages took when they ran, a shared stage counted in each row that uses it; masked_recon
its training and scoring). "n/a (why)" where a figure cannot be computed. One crop grid per scene
(`benchmarks/crop_grid.py`): OUT/<scene>/crops.png, columns = the rows in table order, then the truth.

Resumable: a rerun scores the finished rows without training (the stage runner finds their stages
up to date; masked_recon keeps its `row.json`). Writes OUT/real.md; the last line is JSON.

    python benchmarks/real.py --out OUT --scenes cup_plain cup_edge spinnerf --budget 10
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, default_data, git_commit, vgg_pd_note  # noqa: E402

from coin_cl.atomic import write_text  # noqa: E402
from coin_cl.demo import baseline_config, room_baseline  # noqa: E402
from coin_cl.pipeline.coin import CoInConfig, inpaint  # noqa: E402
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig  # noqa: E402
from coin_cl.pipeline.runner import share_stages  # noqa: E402

# docs/VIRTUAL_OBJECTS.md, "The two cup scenes": (box point x y z, extents x y up, yaw degrees).
CUP_BOXES = {
    "cup_plain": ((4.219, 1.416, 2.08), (1.1, 0.85, 0.95), 25.0),
    "cup_edge": ((2.785, 4.886, 4.866), (1.1, 0.85, 0.95), 25.0),
}
SCENES = ("spinnerf", "cup_plain", "cup_edge")
ROWS = ("default", "naive", "masked_recon", "smooth", "embedded")
KEYS = ("psnr", "m_psnr", "vgg_pd", "m_vgg_pd", "bbox_gmsd", "hf_ratio")
# `coin-cl run`'s --budget default (CoInConfig's): the budget of the default row without --budget
CLI_BUDGET = CoInConfig.budget_minutes


def data_root() -> Path:
    """`$COIN_DATA`, else `../shared/data` beside the repository (`common.default_data`'s folder)."""
    return default_data().parent


def scene_folder(name: str, data: Path, out: Path, extra: dict[str, Path]) -> Path:
    """The scene folder of `name`: SPIn-NeRF's from --data, a cup scene built under OUT/scenes on first
    use (its build time printed), or a folder given with --scene-dir."""
    if name in extra:
        return extra[name]
    if name == "spinnerf":
        path = data / "spinnerf_scene1"
        if not path.is_dir():
            raise SystemExit(f"{path} not found: pass --data DIR holding spinnerf_scene1 (or set COIN_DATA)")
        return path
    path = out / "scenes" / name
    if (path / "scene.json").is_file():
        print(f"[{name}] scene {path} (reused)", flush=True)
        return path
    capture = data / "cup_capture"
    if not capture.is_dir():
        raise SystemExit(f"{capture} not found: pass --data DIR holding cup_capture (or set COIN_DATA)")
    from coin_cl.prepare.virtual_scene import BoxSpec, make_virtual_scene

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{name}.tmp"  # make_virtual_scene's own work folder, left by a killed build
    if tmp.is_dir() and not tmp.is_symlink():
        import shutil

        print(f"[{name}] removing {tmp}, left by an interrupted build", flush=True)
        shutil.rmtree(tmp)

    center, size, yaw = CUP_BOXES[name]
    print(f"[{name}] building the scene: coin-cl make-scene --from-capture {capture} --out {path} --box "
          f"{' '.join(map(str, center + size))} --yaw {yaw:g}", flush=True)  # fmt: skip
    t = time.perf_counter()
    make_virtual_scene(capture, path, BoxSpec(center, size, yaw))
    print(f"[{name}] scene built in {(time.perf_counter() - t) / 60:.1f} min", flush=True)
    return path


def stage_cost(stages: dict) -> float:
    """Minutes the stages took when they ran (this invocation's, or the manifest's for up-to-date ones)."""
    return sum((r.get("seconds") or r.get("seconds_when_run") or 0.0) for r in stages.values()) / 60


def sources_of(run: Path) -> list[str] | None:
    """The stage-1 sources a run used (its `1_inpaint/sources.json`, sorted), None without one."""
    p = run / "1_inpaint" / "sources.json"
    return sorted(set(json.loads(p.read_text()).values())) if p.is_file() else None


def run_default(scene: Path, run: Path, args) -> dict:
    """`coin-cl run SCENE --out RUN` (plus --budget when given; --iters / --prior-seconds only from the
    test's smoke pass-through), through the CLI as a user runs it; a finished folder resumes to nothing."""
    cmd = ["run", str(scene), "--out", str(run)]
    cmd += [] if args.budget is None else ["--budget", f"{args.budget:g}"]
    cmd += [] if args.iters is None else ["--iters", str(args.iters)]
    cmd += [] if args.prior_seconds is None else ["--prior-seconds", f"{args.prior_seconds:g}"]
    print("$ coin-cl " + " ".join(cmd), flush=True)
    subprocess.run([sys.executable, "-m", "coin_cl.cli", *cmd], check=True)
    log = json.loads((run / "log.json").read_text())["stages"]
    metrics = json.loads((run / "eval" / "metrics" / "metrics.json").read_text())["mean"]
    return {**{k: metrics.get(k) for k in KEYS}, "minutes": stage_cost(log), "sources": sources_of(run)}


def base_config(default_run: Path, args) -> CoInConfig:
    """The CLI's config as the default row resolved it: its budget and working resolution (and the
    test's smoke steps), what the rows built beside it start from."""
    plan = json.loads((default_run / "plan.json").read_text())
    cfg = CoInConfig(budget_minutes=plan["key"]["budget_minutes"], resolution=plan["key"]["resolution"],
                     prior_seconds=args.prior_seconds)  # fmt: skip
    return cfg.with_iters(args.iters)


def pipeline_row(scene: Path, run: Path, cfg: CoInConfig) -> dict:
    res = inpaint(scene, run, config=cfg)
    m = res.metrics or {}
    return {**{k: m.get(k) for k in KEYS}, "minutes": stage_cost(res.stages), "sources": sources_of(run)}


def at_default_steps(default_run: Path, cfg: CoInConfig, args) -> CoInConfig:
    """`cfg` with the default row's schedule given explicitly (`coin.steps_from`: its resolution,
    step counts after TE-D's re-plan, scene prior seconds), so a variant trains what the default did;
    its plan takes the default row's measured rates (`rates_from`: nothing probed twice). The variants
    that call this fill stage 1 with a non-learned inpainter (embedded, Telea), for which `coin-cl run`
    leaves TE-D's adversarial phase out and gives its share to the fine-tune phase
    (`coin_plan.adversarial_skip`): so does the variant, with the default row's adversarial steps."""
    cfg = replace(cfg, rates_from=str(default_run))
    if args.iters is not None:  # the smoke pass-through is already explicit
        return cfg
    from coin import steps_from

    cfg = steps_from(default_run, cfg)
    return replace(cfg, iters_ted_finetune=cfg.iters_ted_finetune + cfg.iters_ted_adversarial,
                   iters_ted_adversarial=0)  # fmt: skip


def masked_recon_row(default_run: Path, run: Path, steps: int) -> dict:
    """`demo.room_baseline` on the default row's working-resolution scene (`0_scene/scene`, the views
    and masks its evaluation scored), `steps` 3DGS steps (a killed one resumes from its checkpoint);
    kept in RUN/row.json once finished and reused while the default row's step count is the same."""
    done = run / "row.json"
    if done.is_file():
        row = json.loads(done.read_text())
        if row.get("steps") != steps:  # its checkpoint would resume past or short of this schedule
            raise SystemExit(f"{run} holds masked reconstruction at {row.get('steps')} steps, the "
                             f"default row now trained {steps}: remove {run} to redo it")  # fmt: skip
        return row
    t = time.perf_counter()
    room_baseline(run, default_run / "0_scene" / "scene", steps)
    metrics = json.loads((run / "eval" / "metrics.json").read_text())["mean"]
    row = {**{k: metrics.get(k) for k in KEYS}, "minutes": (time.perf_counter() - t) / 60, "steps": steps,
           "sources": ["none (object pixels left out of the loss)"]}  # fmt: skip
    write_text(done, json.dumps(row, indent=1))
    return row


def truth_photos(scene_dir: Path, data: Path) -> Path | None:
    """The folder of every view's object-absent photo for a virtual-object scene: its capture's
    images, the capture found in `data` by the folder name virtual_object.json gives (a name only:
    no path from the file is followed), else None: only the test views are object-absent."""
    doc = Path(scene_dir) / "virtual_object.json"
    if not doc.is_file():
        return None
    from coin_cl.scene.folder import image_dir

    capture = data / Path(str(json.loads(doc.read_text())["capture"])).name
    if not capture.is_dir():
        raise SystemExit(f"{doc}: its capture {capture.name} is not in {data}; pass --data DIR holding it")
    return image_dir(capture, None)


def not_available(why: str) -> dict[str, float | str]:
    """Both ghost figures of a row that has none, saying why."""
    return dict.fromkeys(("ghost", "ghost_ring"), f"n/a ({why})")


def ghost_figures(runs: dict[str, Path], default_run: Path, out: Path, iters: int,
                  truth: Path | None = None) -> dict[str, dict[str, float | str]]:  # fmt: skip
    """{row: {"ghost", "ghost_ring"}} (`ghost.ghost_of_model`; both "n/a (why)" where there is no
    figure): each row's final model
    against a Scaffold-GS fitted to the object-absent views of the default row's working-resolution
    scene (`ghost.reference_depths`: the test views, or with `truth` (`truth_photos`) every view;
    `iters` steps at least, cached in out/ghost_reference/r<resolution>_i<iters>)."""
    import torch
    from ghost import ghost_of_model, ghost_of_run, reference_depths

    from coin_cl.checkpoint import load_checkpoint
    from coin_cl.gs.model_kinds import model_from_state
    from coin_cl.gs.trainer import CKPT_NAME
    from coin_cl.scene import load_scene

    scene = load_scene(default_run / "0_scene" / "scene")
    if not any(np.asarray(scene.masks[i]).any() for i in scene.test_idx):
        return {r: not_available("no test view with a mask") for r in runs}
    res_key = json.loads((default_run / "plan.json").read_text())["key"]["resolution"]
    depths = reference_depths(scene, out / "ghost_reference" / f"r{res_key:g}_i{iters}", iters, truth)
    res: dict[str, dict[str, float | str]] = {}
    for name, run in runs.items():
        if name == "masked_recon":
            ckpts = sorted((run / "train").rglob(CKPT_NAME), key=lambda p: p.stat().st_mtime)
            if not ckpts:
                res[name] = not_available("no checkpoint")
                continue
            model = model_from_state(load_checkpoint(ckpts[-1])["model"])
            with torch.no_grad():
                res[name] = ghost_of_model(model, scene, depths)
        else:
            res[name] = ghost_of_run(run, scene, depths)
    return res


def run_scene(name: str, scene: Path, out: Path, rows: list[str], args) -> dict:
    default_run = out / "default"
    table: dict[str, dict] = {}
    t = time.perf_counter()
    print(f"[{name}] row default ...", flush=True)
    table["default"] = run_default(scene, default_run, args)
    print(f"[{name}] row default done ({(time.perf_counter() - t) / 60:.1f} min this invocation)", flush=True)
    base = base_config(default_run, args)
    # whole masks: what the default row does with the observed part of each mask is CoIn's, not the
    # naive method's
    naive_cfg = baseline_config(replace(base, inpaint_region="input"), default_run)
    for row in rows:
        if row == "default":
            continue
        run = out / row
        if row == "embedded" and name != "spinnerf":
            table[row] = {"na": "n/a (no dataset inpaints: the default row is the embedded inpainter)"}
            continue
        t = time.perf_counter()
        print(f"[{name}] row {row} ...", flush=True)
        if row == "naive":
            share_stages(default_run, run, ("0_scene", "0_refine", "1_inpaint"))
            table[row] = pipeline_row(scene, run, naive_cfg)
        elif row == "masked_recon":
            table[row] = masked_recon_row(default_run, run, naive_cfg.iters_refgs)
        elif row == "smooth":
            share_stages(default_run, run, ("0_scene", "0_refine"))
            i2d = Inpaint2DConfig(inpainter="telea", use_dataset=False)
            table[row] = pipeline_row(
                scene, run, at_default_steps(default_run, replace(base, inpaint2d=i2d), args)
            )
        elif row == "embedded":
            share_stages(default_run, run, ("0_scene", "0_refine"))
            i2d = Inpaint2DConfig(use_dataset=False)
            table[row] = pipeline_row(
                scene, run, at_default_steps(default_run, replace(base, inpaint2d=i2d), args)
            )
        print(
            f"[{name}] row {row} done ({(time.perf_counter() - t) / 60:.1f} min this invocation)", flush=True
        )
    runs = {r: out / r for r in table if "na" not in table[r]}
    if args.no_ghost:
        ghosts = {r: not_available("--no-ghost") for r in runs}
    else:
        truth = truth_photos(scene, data_root() if args.data is None else args.data)
        ghosts = ghost_figures(runs, default_run, out, args.ghost_iters, truth)
    for r, g in ghosts.items():
        table[r].update(g)
    from crop_grid import grid

    from coin_cl.scene.io import write_png

    write_png(out / "crops.png", grid(list(runs.values())) / 255.0)
    print(f"[{name}] crop grid {out / 'crops.png'}: columns {' | '.join(runs)} | truth", flush=True)
    return table


def cell(v, digits: int = 2, why: str = "not computed") -> str:
    if isinstance(v, str):
        return v
    if v is None:
        return f"n/a ({why})"
    return "nan" if not math.isfinite(v) else f"{v:.{digits}f}"


def markdown(name: str, scene: Path, table: dict, header: str) -> str:
    lines = [f"## {name} ({scene})", "", header, "",
             "| row | PSNR | m-PSNR | VGG-PD | m-VGG-PD | bbox GMSD | HF ratio | ghost | ghost (ring) "
             "| minutes | stage 1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for row, r in table.items():
        if "na" in r:
            lines.append(f"| {row} | " + " | ".join([r["na"]] + ["-"] * 9) + " |")
            continue
        vgg = "weights absent"
        lines.append(
            f"| {row} | {cell(r['psnr'])} | {cell(r['m_psnr'])} | {cell(r['vgg_pd'], 3, vgg)} "
            f"| {cell(r['m_vgg_pd'], 3, vgg)} | {cell(r['bbox_gmsd'], 3)} | {cell(r['hf_ratio'], 3)} "
            f"| {cell(r.get('ghost'), 3)} | {cell(r.get('ghost_ring'), 3)} | {r['minutes']:.1f} "
            f"| {', '.join(r.get('sources') or ['-'])} |"
        )
    lines += ["", f"Crop grid: {name}/crops.png (columns: "
              f"{', '.join(r for r in table if 'na' not in table[r])}, truth)", ""]  # fmt: skip
    return "\n".join(lines)


def summary(tables: dict[str, dict]) -> dict:
    res: dict = {}
    for scene, t in tables.items():
        d, n = t.get("default", {}), t.get("naive", {})
        res[f"{scene}_coin_mpsnr"] = d.get("m_psnr")
        res[f"{scene}_naive_mpsnr"] = n.get("m_psnr")
        res[f"{scene}_coin_vggpd_m"] = d.get("m_vgg_pd")
        res[f"{scene}_naive_vggpd_m"] = n.get("m_vgg_pd")
        g = d.get("ghost")
        res[f"{scene}_coin_ghost"] = g if isinstance(g, float) else None
        for row, r in t.items():
            res[f"{scene}_{row}_minutes"] = r.get("minutes")
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=None, help="folder of spinnerf_scene1 and cup_capture "
                    "(default $COIN_DATA, else ../shared/data beside the repository)")  # fmt: skip
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=ROWS, help="default always runs")
    ap.add_argument("--budget", type=float, default=None,
                    help=f"coin-cl run's --budget for the default row (default: none given, i.e. "
                         f"{CLI_BUDGET:g}); the other rows follow the default row's steps")  # fmt: skip
    ap.add_argument("--ghost-iters", type=int, default=600, help="steps of the ghost reference GS")
    ap.add_argument("--no-ghost", action="store_true", help="skip the ghost figure (n/a in the table)")
    # Smoke-test pass-through (tests/test_benchmarks_real.py): explicit steps instead of the budget's
    # plan, and extra scene folders by name. Not for figures.
    ap.add_argument("--iters", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--prior-seconds", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument(
        "--scene-dir", nargs=2, action="append", default=[], metavar=("NAME", "DIR"), help=argparse.SUPPRESS
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    data = args.data or data_root()
    extra = {n: Path(d) for n, d in args.scene_dir}
    scenes = list(extra) if extra else args.scenes
    rows = ["default"] + [r for r in args.rows if r != "default"]

    from coin_cl.engine import get_runtime

    budget = f"{args.budget:g}" if args.budget is not None else f"{CLI_BUDGET:g} (coin-cl run's default)"
    header = (f"commit {git_commit()}; CPU {cpu_model()}, {os.cpu_count()} cores; OpenCL "
              f"{get_runtime().name}; budget {budget} min"
              + ("" if args.iters is None else f"; smoke steps --iters {args.iters}"))  # fmt: skip
    print(f"# real-capture benchmark: {header}", flush=True)
    tables, parts = {}, []
    for name in scenes:
        scene = scene_folder(name, data, args.out, extra)
        tables[name] = run_scene(name, scene, args.out / name, rows, args)
        parts.append(markdown(name, scene, tables[name], header))
        print("\n" + parts[-1], flush=True)
    note = vgg_pd_note()
    text = "# Real-capture removal\n\n" + "\n".join(parts) + (f"\nVGG-PD: {note}\n" if note else "")
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "real.md", text)
    if note:
        print(f"VGG-PD: {note}")
    result = {**summary(tables), "budget_minutes": args.budget or CLI_BUDGET, "commit": git_commit(),
              "cpu": cpu_model()}  # fmt: skip
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
