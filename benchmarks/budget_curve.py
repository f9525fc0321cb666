"""Benchmark: the pipeline's error against run time. The default command, `coin-cl run SCENE --out DIR
--budget B`, at each budget of `--budgets` (default 3 5 10 20 30) on each scene of `--scenes`:

    spinnerf   spinnerf_scene1 under --data (its 5 object-absent ground-truth views are the test views)
    cup_plain  the virtual box on plain wood made from cup_capture (`real.py`'s `scene_folder`: built
               under OUT/scenes on first use, or given with --scene-dir cup_plain DIR)

Per point (a run folder OUT/<scene>/b<B>): the wall minutes of the whole command (probes, every stage,
eval; what `--budget` promises to hold), m-PSNR, m-VGG-PD (the perceptual distance in the mask's
bounding box), bbox GMSD (`coin_cl.evaluation`) and the ghost figure (`ghost.py`, through `real.py`'s
`ghost_figures`; one reference GS per scene, cached), and m-PSNR and m-VGG-PD once more on the test
views rendered at the capture's own size (RUN/eval/capture: a small working resolution pays for its
blur there). A budget the machine cannot fit is a point
"refused" with the minimum the run named (not kept: a rerun probes again). Writes
OUT/budget_curve.md (the table), OUT/budget_curve.png (m-PSNR and m-VGG-PD against wall minutes,
one line per scene, drawn with OpenCV) and, last, one JSON line.

Resumable: a finished point keeps its figures in OUT/<scene>/b<B>/point.json and is not run again; a
killed one resumes its run folder (its wall minutes are then this invocation's only, flagged
"resumed" in the table).

    python benchmarks/budget_curve.py --out OUT --scenes spinnerf cup_plain --budgets 3 5 10 20 30
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, git_commit  # noqa: E402
from real import data_root, ghost_figures, scene_folder, truth_photos  # noqa: E402

from coin_cl.atomic import write_text  # noqa: E402

SCENES = ("spinnerf", "cup_plain")
BUDGETS = (3.0, 5.0, 10.0, 20.0, 30.0)
KEYS = ("m_psnr", "m_vgg_pd", "bbox_gmsd")
POINT = "point.json"


def run_point(scene: Path, run: Path, budget: float, args) -> dict:
    """One point: `coin-cl run SCENE --out RUN --budget B` through the CLI as a user runs it (its log
    passed through), timed whole; its figures from RUN/eval. A refused budget is {"refused": the
    CLI's line, "minimum": the minutes it named}, probed again by every invocation. A finished point
    is kept in RUN/point.json."""
    done = run / POINT
    if done.is_file():
        point = json.loads(done.read_text())
        if "refused" not in point and "capture_m_psnr" not in point:  # a point from before the figure
            point.update(at_capture(scene, run))
            write_text(done, json.dumps(point, indent=1))
        return point
    resumed = (run / "plan.json").is_file()
    cmd = ["run", str(scene), "--out", str(run), "--budget", f"{budget:g}"]
    cmd += [] if args.iters is None else ["--iters", str(args.iters)]
    cmd += [] if args.prior_seconds is None else ["--prior-seconds", f"{args.prior_seconds:g}"]
    print("$ coin-cl " + " ".join(cmd), flush=True)
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "coin_cl.cli", *cmd], stderr=subprocess.PIPE, text=True)
    last = ""
    for line in proc.stderr:  # the run's log, passed through; its last line names a refusal
        sys.stderr.write(line)
        last = line.strip() or last
    rc = proc.wait()
    wall = (time.perf_counter() - t) / 60
    if rc != 0:
        m = re.search(r"needs at least ([0-9.]+) minutes", last)
        if m is None:
            raise SystemExit(f"coin-cl run failed (exit {rc}) at budget {budget:g}: {last}")
        point = {"budget": budget, "refused": last, "minimum": float(m.group(1))}
    else:
        metrics = json.loads((run / "eval" / "metrics" / "metrics.json").read_text())["mean"]
        point = {
            "budget": budget,
            "wall_minutes": wall,
            "resumed": resumed,
            **{k: metrics.get(k) for k in KEYS},
        }
    if "refused" in point:  # not kept: a rerun on a quieter machine probes again (seconds)
        return point
    if not args.no_ghost:
        truth = truth_photos(scene, data_root() if args.data is None else args.data)
        point.update(ghost_figures({"run": run}, run, run.parent, args.ghost_iters, truth)["run"])
    point.update(at_capture(scene, run))
    write_text(done, json.dumps(point, indent=1))
    return point


def at_capture(scene: Path, run: Path) -> dict:
    """{"capture_m_psnr", "capture_m_vgg_pd"}: the run's final model scored on the test views at the
    capture's own resolution (RUN/eval/capture, written by the eval stage; scored here for a run folder
    made before it was: `eval_stage.score_at_capture`); {} when the run worked at the capture's size."""
    doc = run / "eval" / "capture" / "metrics.json"
    if not doc.is_file():
        from coin_cl.gs.model_kinds import model_from_state
        from coin_cl.gs.trainer import CKPT_NAME
        from coin_cl.pipeline.eval_stage import score_at_capture
        from coin_cl.pipeline.run_inputs import capture_views
        from coin_cl.pipeline.stages import load_model
        from coin_cl.scene import load_scene

        if json.loads((run / "plan.json").read_text())["key"]["resolution"] == 1.0:
            return {}
        final = json.loads((run / "eval" / "manifest.json").read_text())["result"]["final_stage"]
        model = load_model(run / final, CKPT_NAME, model_from_state)
        score_at_capture(model, capture_views(load_scene(scene)), doc.parent)
    mean = json.loads(doc.read_text())["mean"]
    return {"capture_m_psnr": mean["m_psnr"], "capture_m_vgg_pd": mean["m_vgg_pd"]}


def cell(v, digits: int = 2) -> str:
    if isinstance(v, str):
        return v
    if v is None:
        return "n/a"
    return "nan" if not math.isfinite(v) else f"{v:.{digits}f}"


def markdown(curves: dict[str, list[dict]], header: str) -> str:
    cols = ("| scene | budget | wall min | wall / budget | m-PSNR | m-VGG-PD | bbox GMSD | ghost "
            "| m-PSNR at capture size | m-VGG-PD at capture size |")  # fmt: skip
    lines = [header, "", cols, "|---" * 10 + "|"]
    for scene, points in curves.items():
        for p in points:
            b = p["budget"]
            if "refused" in p:
                lines.append(f"| {scene} | {b:g} | refused: needs {p['minimum']:g} min here |" + " - |" * 7)
                continue
            wall = f"{p['wall_minutes']:.1f}" + (" (resumed)" if p.get("resumed") else "")
            ratio = p["wall_minutes"] / b
            lines.append(f"| {scene} | {b:g} | {wall} | {ratio:.2f} | {cell(p.get('m_psnr'))} "
                         f"| {cell(p.get('m_vgg_pd'), 3)} | {cell(p.get('bbox_gmsd'), 3)} "
                         f"| {cell(p.get('ghost'), 3)} | {cell(p.get('capture_m_psnr'))} "
                         f"| {cell(p.get('capture_m_vgg_pd'), 3)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


# The plot's colours (BGR), one per scene in order.
COLOURS = ((200, 80, 30), (30, 130, 230), (60, 160, 60), (150, 60, 170))


def plot(curves: dict[str, list[dict]], path: Path) -> None:
    """Two panels (m-PSNR, m-VGG-PD) against wall minutes, one polyline per scene, each point labelled
    with its budget; written as PNG (OpenCV draws it: matplotlib is not a dependency)."""
    import cv2

    w, h, pad = 520, 360, 60
    img = np.full((h + 40, 2 * w, 3), 255, np.uint8)
    done = {s: [p for p in ps if "refused" not in p] for s, ps in curves.items()}
    xs = [p["wall_minutes"] for ps in done.values() for p in ps] or [0.0, 1.0]
    x0, x1 = 0.0, max(xs) * 1.05 or 1.0
    for panel, (key, label) in enumerate((("m_psnr", "m-PSNR (dB)"), ("m_vgg_pd", "m-VGG-PD"))):
        ox = panel * w
        ys = [
            p[key]
            for ps in done.values()
            for p in ps
            if isinstance(p.get(key), float) and math.isfinite(p[key])
        ]
        y0, y1 = (min(ys), max(ys)) if ys else (0.0, 1.0)
        y0, y1 = (y0 - 0.5, y1 + 0.5) if y1 - y0 < 1e-6 else (y0 - 0.05 * (y1 - y0), y1 + 0.05 * (y1 - y0))

        def at(x: float, y: float, ox: int = ox, y0: float = y0, y1: float = y1) -> tuple[int, int]:
            return (
                ox + pad + int((x - x0) / (x1 - x0) * (w - 2 * pad)),
                h - pad + 20 - int((y - y0) / (y1 - y0) * (h - 2 * pad)),
            )

        cv2.rectangle(img, at(x0, y0), at(x1, y1), (0, 0, 0), 1)
        cv2.putText(img, label, (ox + pad, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, "wall minutes", (ox + w // 2 - 50, h + 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0),
                    1,
                    cv2.LINE_AA)  # fmt: skip
        for v, pos in ((x0, at(x0, y0)), (x1, at(x1, y0))):
            cv2.putText(
                img, f"{v:.0f}", (pos[0] - 8, pos[1] + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1
            )
        for v, pos in ((y0, at(x0, y0)), (y1, at(x0, y1))):
            cv2.putText(
                img, f"{v:.2f}", (pos[0] - 55, pos[1] + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1
            )
        for i, (scene, ps) in enumerate(done.items()):
            col = COLOURS[i % len(COLOURS)]
            pts = [(at(p["wall_minutes"], p[key]), p["budget"])
                   for p in sorted(ps, key=lambda p: p["wall_minutes"])
                   if isinstance(p.get(key), float) and math.isfinite(p[key])]  # fmt: skip
            for (a, _), (b, _) in zip(pts, pts[1:]):
                cv2.line(img, a, b, col, 2, cv2.LINE_AA)
            for q, budget in pts:
                cv2.circle(img, q, 4, col, -1, cv2.LINE_AA)
                cv2.putText(img, f"b{budget:g}", (q[0] + 5, q[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1)
            cv2.putText(img, scene, (ox + w - pad - 90, 50 + 18 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, col, 1,
                        cv2.LINE_AA)  # fmt: skip
    from coin_cl.scene.io import write_png

    write_png(path, img[:, :, ::-1] / 255.0)


def summary(curves: dict[str, list[dict]]) -> dict:
    res: dict = {"cpu": cpu_model()}
    for scene, points in curves.items():
        for p in points:
            tag = f"{scene}_b{p['budget']:g}"
            if "refused" in p:
                res[f"{tag}_refused_minimum"] = p["minimum"]
                continue
            res[f"{tag}_wall_minutes"] = round(p["wall_minutes"], 2)
            for k in (*KEYS, "ghost", "capture_m_psnr", "capture_m_vgg_pd"):
                v = p.get(k)
                res[f"{tag}_{k}"] = v if isinstance(v, float) else None
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=None, help="folder of spinnerf_scene1 and cup_capture "
                    "(default: $COIN_DATA, else ../shared/data)")  # fmt: skip
    ap.add_argument("--scenes", nargs="+", default=None, choices=SCENES,
                    help=f"default: {' '.join(SCENES)}, or only the --scene-dir ones when given")  # fmt: skip
    ap.add_argument("--budgets", nargs="+", type=float, default=list(BUDGETS), help="minutes, one point each")
    ap.add_argument("--ghost-iters", type=int, default=600, help="steps of the ghost reference GS")
    ap.add_argument("--no-ghost", action="store_true", help="skip the ghost figure")
    # a scene folder already built (e.g. cup_plain under another benchmark's OUT/scenes)
    ap.add_argument("--scene-dir", nargs=2, action="append", default=[], metavar=("NAME", "DIR"),
                    help="use DIR as scene NAME instead of building or finding it")  # fmt: skip
    # the smoke test's pass-through (explicit step counts; not a curve)
    ap.add_argument("--iters", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--prior-seconds", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    bad = [b for b in args.budgets if not (math.isfinite(b) and b > 0)]
    if bad:
        raise SystemExit(f"--budgets must be positive minutes, got {bad}")
    data = args.data or data_root()
    extra = {name: Path(d) for name, d in args.scene_dir}
    named = args.scenes if args.scenes is not None else ([] if extra else list(SCENES))
    scenes = named + [n for n in extra if n not in named]
    curves: dict[str, list[dict]] = {}
    for name in scenes:
        scene = scene_folder(name, data, args.out, extra)
        curves[name] = []
        for b in args.budgets:
            t = time.perf_counter()
            print(f"[{name}] budget {b:g} ...", flush=True)
            curves[name].append(run_point(scene, args.out / name / f"b{b:g}", b, args))
            print(f"[{name}] budget {b:g} done ({(time.perf_counter() - t) / 60:.1f} min this invocation)",
                  flush=True)  # fmt: skip
    header = (f"# The pipeline's error against run time\n\nMachine: {cpu_model()}, {os.cpu_count()} cores; "
              f"commit {git_commit()}. Command: `coin-cl run SCENE --out DIR --budget B`.")  # fmt: skip
    write_text(args.out / "budget_curve.md", markdown(curves, header))
    plot(curves, args.out / "budget_curve.png")
    print(markdown(curves, header), flush=True)
    print(json.dumps(summary(curves)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
