"""`coin-cl prepare` on the shared SPIn-NeRF scene, scored against the dataset's own poses and masks.

Usage: python benchmarks/prepare.py [--data DIR] [--out DIR] [--width 504] [--fresh]

1. SfM from the images alone (images_4/, all 39 views): registered views, rotation and camera-centre
   errors after a similarity alignment to the LLFF poses in poses_bounds.npy (centre errors also as
   a fraction of the reference cameras' spread), minutes.
2. Masks from the dataset label of ONE view (the one `choose_reference` picks on the dataset
   folder), given as a mask annotation (as a user would paint it on the photo), propagated to the
   other training views: IoU against each view's dataset label. The labels are drawn on the
   distorted photos; they are resized to the working size and undistorted with the SfM camera
   before the comparison, so both live in the prepared images' geometry.
Prints a table; the LAST line is one JSON object {registered, rot_err_deg, centre_err, mask_iou_mean,
mask_iou_min, prepare_minutes, prepared_mpsnr, dataset_mpsnr, ...}. The m-PSNR pair (a `coin-cl run`
on the prepared folder beside one on the dataset's folder) is not measured here and stays null: a
run takes about 20 minutes per folder at a small budget, and the prepared folder would first need
the dataset's 5 object-absent views held out and its poses aligned to score them.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import cpu_model, default_data, git_commit, write_result  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    import numpy as np

    import coin_cl
    from coin_cl.pipeline.reference import choose_reference
    from coin_cl.prepare import Annotation, PropagateConfig, SfmConfig, make_masks, run_sfm
    from coin_cl.prepare.align import pose_errors, relative_rotation_errors
    from coin_cl.prepare.propagate import iou
    from coin_cl.prepare.scene_masks import load_prepared
    from coin_cl.scene.colmap import Undistorter, pinhole_for, read_cameras
    from coin_cl.scene.types import resize_mask

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=default_data())
    ap.add_argument("--out", type=Path, default=Path("runs/bench_prepare"))
    ap.add_argument("--width", type=int, default=504, help="working width (the images are 1008 wide)")
    ap.add_argument("--max-features", type=int, default=SfmConfig.max_features)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fresh", action="store_true", help="delete OUT/scene first (else a run resumes)")
    args = ap.parse_args(argv)
    photos = args.data / "images_4"
    scene_dir = args.out / "scene"
    if args.fresh and scene_dir.exists():
        import shutil

        shutil.rmtree(scene_dir)
    print(f"# prepare benchmark  commit {git_commit()}  CPU {cpu_model()}  ({os.cpu_count()} logical cores)")
    print("# OpenCL: not used (pycolmap SIFT/matching/mapping on the CPU, OpenCV GrabCut)")
    print(f"# data {args.data}  working width {args.width}  max features {args.max_features}")

    t0 = time.perf_counter()
    cfg = SfmConfig(width=args.width, max_features=args.max_features, num_threads=args.threads)
    report = run_sfm(photos, scene_dir, cfg)
    t_sfm = time.perf_counter() - t0

    dataset = coin_cl.load_scene(args.data)
    prepared = load_prepared(scene_dir)
    by_stem = {Path(n).stem: i for i, n in enumerate(prepared.names)}
    common = [i for i, n in enumerate(dataset.names) if Path(n).stem in by_stem]
    err = pose_errors(
        [prepared.cameras[by_stem[Path(dataset.names[i]).stem]].viewmat for i in common],
        [dataset.cameras[i].viewmat for i in common],
    )
    rel = relative_rotation_errors(
        [prepared.cameras[by_stem[Path(dataset.names[i]).stem]].viewmat for i in common],
        [dataset.cameras[i].viewmat for i in common],
    )
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

    # the dataset labels in the prepared geometry: resized, then undistorted with the SfM camera
    cam = next(iter(read_cameras(scene_dir / ".prepare" / "sparse" / "best").values()))
    K, dist, fisheye = pinhole_for(cam, "SfM camera")
    und = Undistorter(K, dist, fisheye, cam.width, cam.height) if dist is not None else None
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
    print(f"| registered views | {len(report.registered)} / {n_photos} | all |")
    rot = f"{err.median_rot_deg:.3f} / {err.rot_deg.max():.3f}"
    print(f"| rotation error after the similarity (on centres), median / max (deg) | {rot} | < 1 median |")
    print(f"| relative rotation error over all view pairs, median / max (deg) | "
          f"{np.median(rel):.3f} / {rel.max():.3f} | |")  # fmt: skip
    print(
        f"| camera-centre error, median (dataset units) | {err.median_centre:.4g} "
        f"({err.median_centre / spread:.2%} of the camera spread {spread:.3g}) | |"
    )
    print(f"| mean reprojection error (px at {report.width} wide) | {report.mean_reproj_error:.3f} | |")
    score = f"{ious.mean():.3f} / {ious.min():.3f}"
    print(f"| mask IoU mean / min ({len(ious)} views) | {score} | >= 0.85 / >= 0.6 |")
    mins = f"{t_sfm / 60:.2f} / {t_masks / 60:.2f} / {(t_sfm + t_masks) / 60:.2f}"
    print(f"| minutes: SfM / masks / total | {mins} | < 10 |")
    print(f"| SfM seconds per step | {', '.join(f'{k} {v:.0f}' for k, v in report.seconds.items())} | |")
    summary = {
        "registered": len(report.registered),
        "n_photos": n_photos,
        "rot_err_deg": round(err.median_rot_deg, 4),
        "rot_err_deg_max": round(float(err.rot_deg.max()), 4),
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
    }
    write_result(args.out, summary, rows)
    return summary


if __name__ == "__main__":
    main()
