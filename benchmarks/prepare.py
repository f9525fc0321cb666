"""`coin-cl prepare` on the shared SPIn-NeRF scene, scored against the dataset's own poses and masks,
then CoIn on the prepared folder beside CoIn on the dataset's folder.

Usage: python benchmarks/prepare.py [--data DIR] [--out DIR] [--width 504] [--fresh] [--run-budget 4]

1. SfM from the images alone (images_4/): the 34 object-present training photos are mapped; the 5
   object-absent test photos are held out (`--holdout`: localized in that model, never mapped,
   no points from them) and carry the dataset's test_label masks (cropped to the photo, resized,
   undistorted). Registered views, rotation and camera-centre errors after a similarity alignment
   to the LLFF poses in poses_bounds.npy (centre errors also as a fraction of the reference
   cameras' spread), the held-out views' own errors, minutes.
2. Masks from the dataset label of ONE view (the one `choose_reference` picks on the dataset
   folder), given as a mask annotation (as a user would paint it on the photo), propagated to the
   other training views: IoU against each view's dataset label. The labels are drawn on the
   distorted photos; they are resized to the working size and undistorted with the SfM camera
   before the comparison, so both live in the prepared images' geometry.
3. (`--run-budget B`, 0 skips) `coin_cl.inpaint` (what `coin-cl run` runs) on the dataset's folder at
   B minutes, then on the prepared folder with the step counts the first run trained (the same
   work, whatever the machine's load), both at 504x284 with the settings of RUN_SETTINGS; each
   scored by its own eval stage on the 5 held-out views against its own folder's truth and test
   masks: m-PSNR, HF ratio, GMSD. Floor: the prepared run within 1 dB m-PSNR of the dataset run.
Prints tables; the LAST line is one JSON object {registered, rot_err_deg, centre_err, mask_iou_mean,
mask_iou_min, prepare_minutes, prepared_mpsnr, dataset_mpsnr, ...}.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import cpu_model, default_data, git_commit, write_result  # noqa: E402

# Settings both CoIn runs share, so that they differ only in what `coin-cl prepare` made (poses,
# masks, sparse points, undistorted images): the captured images at 504x284, the whole masks
# inpainted (the "auto" estimate could pick differently for the two folders), and no dataset priors
# (the prepared folder has no LaMa inpaints or inpainted depth, so the dataset run does without them
# too: both fill with the embedded inpainter and train the depth prior's auxiliary GS).
RUN_SETTINGS = {"inpaint_region": "input", "seed": 0}


def coin_run(scene, out: Path, ref: str, budget: float, resolution: float, steps: dict | None = None) -> dict:
    """One `coin_cl.inpaint` run (what `coin-cl run` calls) on `scene` (a folder or a Scene) into
    `out`: the budget's plan, or explicit `steps` {refgs, ted_finetune, ted_adversarial,
    prior_seconds}. Returns {metrics (mean over the test views), per_view, steps trained, minutes
    (the stages' own seconds, so a resumed run reports the run that made it)}."""
    from coin_cl.pipeline.coin import CoInConfig, inpaint

    cfg = CoInConfig(resolution=resolution, **RUN_SETTINGS)
    if steps is not None:
        cfg = CoInConfig(
            resolution=resolution, iters_refgs=steps["refgs"], iters_ted_finetune=steps["ted_finetune"],
            iters_ted_adversarial=steps["ted_adversarial"], prior_seconds=steps["prior_seconds"],
            **RUN_SETTINGS,
        )  # fmt: skip
    inpaint(scene, out, reference=ref, budget=budget, config=cfg)
    minutes = sum(json.loads(m.read_text()).get("seconds", 0.0) for m in out.glob("*/manifest.json")) / 60
    doc = json.loads((out / "eval" / "metrics" / "metrics.json").read_text())
    return {"metrics": doc["mean"], "per_view": doc["per_view"], "steps": run_steps(out),
            "minutes": round(minutes, 2)}  # fmt: skip


def run_steps(out: Path) -> dict:
    """The steps a finished run trained (a GS stage's time cap can stop it before its plan): Ref-GS's
    from its manifest, TE-D's two phases from theirs, and the scene prior's planned seconds."""
    refgs = json.loads((out / "2_refgs" / "manifest.json").read_text())["result"]
    ted = json.loads((out / "4_ted" / "manifest.json").read_text())["result"]
    plan = json.loads((out / "plan.json").read_text())
    return {"refgs": int(refgs["steps"]), "ted_finetune": int(ted["finetune"]["step"]),
            "ted_adversarial": int(ted["adversarial"]["step"]),
            "prior_seconds": float(plan["prior_seconds"])}  # fmt: skip


def holdout_masks(dataset, out: Path) -> tuple[list[str], Path]:
    """The dataset's test views (names) and their region masks (test_label, cropped to the photo
    height by the loader) written as out/<stem>.png, as a user gives them with --holdout-masks."""
    from coin_cl.scene.io import write_png

    out.mkdir(parents=True, exist_ok=True)
    for i in dataset.test_idx:
        write_png(out / f"{Path(dataset.names[i]).stem}.png", dataset.masks[i].astype("uint8") * 255)
    return [dataset.names[i] for i in dataset.test_idx], out


def main(argv: list[str] | None = None) -> dict:
    import numpy as np

    import coin_cl
    from coin_cl.pipeline.reference import choose_reference
    from coin_cl.prepare import Annotation, PropagateConfig, SfmConfig, make_masks, run_sfm
    from coin_cl.prepare.align import pose_errors, relative_rotation_errors
    from coin_cl.prepare.holdout import write_holdout_masks
    from coin_cl.prepare.propagate import iou
    from coin_cl.prepare.scene_masks import load_prepared
    from coin_cl.scene.colmap import Undistorter, pinhole_for, read_cameras, read_model
    from coin_cl.scene.types import resize_mask

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--out", type=Path, default=Path("runs/bench_prepare"))
    ap.add_argument("--width", type=int, default=504, help="working width (the images are 1008 wide)")
    ap.add_argument("--max-features", type=int, default=SfmConfig.max_features)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fresh", action="store_true", help="delete OUT/scene first (else a run resumes)")
    ap.add_argument("--run-budget", type=float, default=4.0,
                    help="minutes of the dataset-folder CoIn run (the prepared run trains as many steps); "
                         "0: no runs")  # fmt: skip
    ap.add_argument("--thin-control", action="store_true",
                    help="a third run: the dataset's folder, its sparse points thinned at random to the "
                         "prepared model's count (same steps): the points' share of a gap")  # fmt: skip
    args = ap.parse_args(argv)
    photos = args.data / "images_4"
    scene_dir = args.out / "scene"
    if args.fresh and scene_dir.exists():
        import shutil

        shutil.rmtree(scene_dir)
    print(f"# prepare benchmark  commit {git_commit()}  CPU {cpu_model()}  ({os.cpu_count()} logical cores)")
    print("# OpenCL: not used by the preparation (pycolmap SIFT/matching/mapping, OpenCV GrabCut: CPU);")
    print("#   the CoIn runs use coin-cl's default OpenCL device")
    print(f"# data {args.data}  working width {args.width}  max features {args.max_features}")

    dataset = coin_cl.load_scene(args.data)
    held, held_dir = holdout_masks(dataset, args.out / "holdout_masks")
    t0 = time.perf_counter()
    cfg = SfmConfig(width=args.width, max_features=args.max_features, num_threads=args.threads)
    report = run_sfm(photos, scene_dir, cfg, holdout=held)
    t_sfm = time.perf_counter() - t0
    sfm_cam = next(iter(read_cameras(scene_dir / ".prepare" / "sparse" / "best").values()))
    write_holdout_masks(scene_dir, sorted(report.held_out), held_dir, sfm_cam)

    model = read_model(scene_dir / "sparse" / "0")
    pose = {Path(n).stem: vm for n, (_, vm) in model.images.items()}
    common = [i for i, n in enumerate(dataset.names) if Path(n).stem in pose]
    est = [pose[Path(dataset.names[i]).stem] for i in common]
    ref_vm = [dataset.cameras[i].viewmat for i in common]
    err = pose_errors(est, ref_vm)
    rel = relative_rotation_errors(est, ref_vm)
    is_held = np.array([i in dataset.test_idx for i in common])
    centres = np.array([dataset.cameras[i].center for i in common])
    spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))

    # masks from the reference view's label only
    ref = choose_reference(dataset)
    ref_name = dataset.names[ref]
    label_dir = photos / "label"
    t1 = time.perf_counter()
    result = make_masks(
        scene_dir, Annotation(view=Path(ref_name).stem, mask=label_dir / ref_name), PropagateConfig()
    )
    t_masks = time.perf_counter() - t1
    prepared = load_prepared(scene_dir)  # the training views, in the order of result.masks
    by_stem = {Path(n).stem: i for i, n in enumerate(prepared.names)}

    # the dataset labels in the prepared geometry: resized, then undistorted with the SfM camera
    K, dist, fisheye = pinhole_for(sfm_cam, "SfM camera")
    und = Undistorter(K, dist, fisheye, sfm_cam.width, sfm_cam.height) if dist is not None else None
    rows = {}
    print()
    print(f"Masks from the label of view {ref_name} (dataset index {ref}) only:")
    print("| view | IoU | source | consensus IoU |")
    print("|---|---|---|---|")
    for i in dataset.train_idx:
        n = dataset.names[i]
        if i == ref or Path(n).stem not in by_stem:
            continue
        v = by_stem[Path(n).stem]
        gt = resize_mask(dataset.masks[i], prepared.cameras[v].width, prepared.cameras[v].height)
        gt = und.mask(gt) if und is not None else gt
        score = iou(result.masks[v], gt)
        rows[n] = {"iou": round(score, 4), "source": result.source[v], "consensus_iou": result.consistency[v]}
        print(f"| {n} | {score:.3f} | {result.source[v]} | {result.consistency[v]:.3f} |")
    ious = np.array([r["iou"] for r in rows.values()])

    print()
    print("| quantity | value | floor |")
    print("|---|---|---|")
    n_photos = report.n_photos
    n_posed = len(report.registered) + len(report.held_out)
    print(f"| posed views: mapped + held out (localized) | {len(report.registered)} + "
          f"{len(report.held_out)} = {n_posed} / {n_photos} | all |")  # fmt: skip
    rot = f"{err.median_rot_deg:.3f} / {err.rot_deg.max():.3f}"
    print(f"| rotation error after the similarity (on centres), median / max (deg) | {rot} | < 1 median |")
    print(f"| relative rotation error over all view pairs, median / max (deg) | "
          f"{np.median(rel):.3f} / {rel.max():.3f} | |")  # fmt: skip
    print(
        f"| camera-centre error, median (dataset units) | {err.median_centre:.4g} "
        f"({err.median_centre / spread:.2%} of the camera spread {spread:.3g}) | |"
    )
    if is_held.any():
        print(f"| held-out views: rotation error max (deg) / centre error max | "
              f"{err.rot_deg[is_held].max():.3f} / {err.centre[is_held].max():.4g} | |")  # fmt: skip
    print(f"| mean reprojection error (px at {report.width} wide) | {report.mean_reproj_error:.3f} | |")
    score = f"{ious.mean():.3f} / {ious.min():.3f}"
    print(f"| mask IoU mean / min ({len(ious)} views) | {score} | >= 0.85 / >= 0.6 |")
    mins = f"{t_sfm / 60:.2f} / {t_masks / 60:.2f} / {(t_sfm + t_masks) / 60:.2f}"
    print(f"| minutes: SfM / masks / total | {mins} | < 10 |")
    print(f"| SfM seconds per step | {', '.join(f'{k} {v:.0f}' for k, v in report.seconds.items())} | |")
    summary = {
        "registered": n_posed,
        "mapped": len(report.registered),
        "held_out_localized": len(report.held_out),
        "n_photos": n_photos,
        "rot_err_deg": round(err.median_rot_deg, 4),
        "rot_err_deg_max": round(float(err.rot_deg.max()), 4),
        "held_out_rot_err_deg_max": round(float(err.rot_deg[is_held].max()), 4) if is_held.any() else None,
        "rel_rot_err_deg": round(float(np.median(rel)), 4),
        "centre_err": round(err.median_centre, 5),
        "centre_err_rel": round(err.median_centre / spread, 5),
        "mask_iou_mean": round(float(ious.mean()), 4),
        "mask_iou_min": round(float(ious.min()), 4),
        "prepare_minutes": round((t_sfm + t_masks) / 60, 3),
        "sfm_minutes": round(t_sfm / 60, 3),
        "masks_minutes": round(t_masks / 60, 3),
        "width": report.width,
        "reference_view": ref_name,
        "prepared_mpsnr": None,
        "dataset_mpsnr": None,
        "commit": git_commit(),
        "cpu": cpu_model(),
    }
    if args.run_budget > 0:
        summary.update(compare_runs(args, dataset, scene_dir, ref_name, rows))
    write_result(args.out, summary, rows)
    return summary


def compare_runs(args, dataset, scene_dir: Path, ref_name: str, rows: dict) -> dict:
    """CoIn on the dataset's folder (without its priors) at the budget, then on the prepared folder
    with the same step counts; both scored on the held-out views. Prints the table; returns the
    summary's run entries."""
    import numpy as np

    import coin_cl

    scale = args.width / dataset.cameras[0].width  # the prepared images are already at the working width
    runs = {}
    print()
    print(f"CoIn runs (reference view {ref_name}, budget {args.run_budget:g} min for the dataset run):")
    ref_name = Path(ref_name).stem
    data_scene = coin_cl.load_scene(args.data, priors=False)
    runs["dataset"] = coin_run(data_scene, args.out / "run_dataset", ref_name, args.run_budget, scale)
    steps = runs["dataset"]["steps"]
    runs["prepared"] = coin_run(scene_dir, args.out / "run_prepared", ref_name, args.run_budget, 1.0, steps)
    if args.thin_control:
        from dataclasses import replace

        n = len(coin_cl.load_scene(scene_dir).points)
        keep = np.sort(np.random.default_rng(0).choice(len(data_scene.points), n, replace=False))
        cols = None if data_scene.colors is None else data_scene.colors[keep]
        thin = replace(data_scene, points=data_scene.points[keep], colors=cols)
        print(f"(dataset_thin: the dataset's folder with {n} of its {len(data_scene.points)} points)")
        runs["dataset_thin"] = coin_run(thin, args.out / "run_dataset_thin", ref_name, args.run_budget,
                                        scale, steps)  # fmt: skip
    print("| folder | m-PSNR | HF ratio | GMSD (bbox) | PSNR | minutes | steps (Ref-GS, TE-D ft, TE-D adv) |")
    print("|---|---|---|---|---|---|---|")
    for k, r in runs.items():
        m, st = r["metrics"], r["steps"]
        ted = f"{st['ted_finetune']}, {st['ted_adversarial']}"
        print(f"| {k} | {m['m_psnr']:.2f} | {m['hf_ratio']:.3f} | {m['bbox_gmsd']:.3f} | {m['psnr']:.2f} | "
              f"{r['minutes']:.1f} | {st['refgs']}, {ted} |")  # fmt: skip
        rows[f"run_{k}"] = r
    gap = runs["prepared"]["metrics"]["m_psnr"] - runs["dataset"]["metrics"]["m_psnr"]
    print(f"| prepared - dataset m-PSNR | {gap:+.2f} dB | floor: at least -1 dB |")
    out = {"run_budget_minutes": args.run_budget, "run_steps": steps, "mpsnr_gap": round(gap, 3),
           "floor_mpsnr_within_1db": bool(gap >= -1.0)}  # fmt: skip
    for k, r in runs.items():
        out[f"{k}_mpsnr"] = round(r["metrics"]["m_psnr"], 4)
        out[f"{k}_hf_ratio"] = round(r["metrics"]["hf_ratio"], 4)
        out[f"{k}_gmsd"] = round(r["metrics"]["bbox_gmsd"], 4)
        out[f"{k}_run_minutes"] = r["minutes"]
    return out


if __name__ == "__main__":
    main()
