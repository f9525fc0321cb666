"""`coin-cl prepare PHOTOS_DIR --out SCENE_DIR`: photos -> posed scene (+ masks from one
annotation), over `coin_cl.prepare.prepare`."""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_cl.cli import values


def add_commands(subparsers) -> None:
    """Register `prepare` on the `coin-cl` subparsers."""
    from coin_cl.prepare import SfmConfig

    d = SfmConfig()
    p = subparsers.add_parser(
        "prepare",
        help="structure from motion on a folder of photos, and object masks from one annotation",
        description="Poses the photos with pycolmap and writes SCENE_DIR in the plain COLMAP layout "
        "(images/, sparse/0 PINHOLE, masks/) that `coin-cl run` reads, with prepare_report.txt. "
        "Given the object in one view (--box, --scribble or --mask), writes its mask in every view "
        "and masks_contact_sheet.png. A second run resumes from what exists.",
    )
    p.add_argument("photos", type=Path, help="folder of photos of one scene (.jpg/.png, one aspect ratio)")
    p.add_argument("--out", type=values.folder, required=True,
                   help="scene folder to write: new, empty, one prepare made (it resumes), or the "
                        "photos' parent (the photos are kept; the images go to "
                        "images_prepared/)")  # fmt: skip
    p.add_argument("--replace", action="store_true",
                   help="prepare into a folder that holds a scene prepare did not make (sparse/0, "
                        "images/): its images/, sparse/0 and masks/ are replaced; the photos are only "
                        "read, never replaced")  # fmt: skip
    p.add_argument("--width", type=int, default=d.width,
                   help=f"working width in px; wider photos are downscaled (default {d.width})")  # fmt: skip
    p.add_argument("--exhaustive-max", type=int, default=d.exhaustive_max,
                   help="match all pairs up to this many photos, else neighbours by name "
                        f"(default {d.exhaustive_max})")  # fmt: skip
    p.add_argument(
        "--threads", type=int, default=d.num_threads, help=f"CPU threads (default {d.num_threads})"
    )
    p.add_argument("--holdout", nargs="+", default=[], metavar="PHOTO",
                   help="photos to pose but not train on (e.g. object-absent ground truth): localized in "
                        "the model of the others, written as test views (sparse/0/test.txt)")  # fmt: skip
    p.add_argument("--holdout-masks", type=Path, default=None, metavar="DIR",
                   help="region masks of the held-out photos, drawn on them (DIR/<name>.png): the "
                        "region `coin-cl eval` scores")  # fmt: skip
    a = p.add_mutually_exclusive_group()
    a.add_argument("--box", nargs=5, metavar=("VIEW", "X0", "Y0", "X1", "Y1"),
                   help="the object's box in one photo (name or index), in that photo's pixels")  # fmt: skip
    a.add_argument("--scribble", nargs=2, metavar=("VIEW", "IMAGE"),
                   help="strokes drawn on the object (non-zero pixels) in one photo")  # fmt: skip
    a.add_argument("--mask", nargs=2, metavar=("VIEW", "IMAGE"), help="the object's mask in one photo")
    p.set_defaults(func=cmd_prepare)


def cmd_prepare(args: argparse.Namespace) -> int:
    from coin_cl.cli.guard import output_folder
    from coin_cl.outdir import OutputFolderError, check_output
    from coin_cl.prepare import Annotation, SfmConfig, prepare

    ann = None
    if args.box:
        try:
            box = tuple(float(v) for v in args.box[1:])
        except ValueError as exc:
            raise ValueError(f"--box VIEW X0 Y0 X1 Y1 needs four numbers, got {args.box[1:]}") from exc
        ann = Annotation(view=args.box[0], box=box)
    elif args.scribble:
        ann = Annotation(view=args.scribble[0], scribble=Path(args.scribble[1]))
    elif args.mask:
        ann = Annotation(view=args.mask[0], mask=Path(args.mask[1]))
    cfg = SfmConfig(width=args.width, exhaustive_max=args.exhaustive_max, num_threads=args.threads)
    # The photos' own folder inside --out (COLMAP's layout: --out its parent) is not content.
    photos_here = args.photos.resolve().parent == args.out.resolve()
    ignore = (args.photos.resolve().name,) if photos_here else ()
    try:
        check_output(args.out, "prepare", ignore, adopt=args.replace)
    except OutputFolderError as exc:
        scene = [f"{n}/" for n in ("sparse", "images") if (args.out / n).exists() and n not in ignore]
        if not scene:
            raise
        raise OutputFolderError(
            f"{args.out} holds a scene coin-cl prepare did not make ({', '.join(scene)}): add "
            "--replace to replace its images/, sparse/0 and masks/ (the photos are never touched), "
            "or choose another --out"
        ) from exc
    with output_folder(args.out, "prepare", ignore, adopt=args.replace):
        report, masks = prepare(args.photos, args.out, ann, sfm=cfg, holdout=args.holdout,
                                holdout_masks=args.holdout_masks)  # fmt: skip
    images = "images_prepared" if (args.out / "images_prepared").is_dir() else "images"
    print(report.text(), end="")
    print(f"wrote {args.out}/{images}, {args.out}/sparse/0, {args.out}/prepare_report.txt")
    if masks is not None:
        flagged = [i for i, s in enumerate(masks.source) if s == "consensus"]
        print(f"wrote {args.out}/masks ({len(masks.masks)} views, {len(flagged)} to check) and "
              f"{args.out}/masks_contact_sheet.png")  # fmt: skip
    else:
        print("no annotation given: add --box VIEW X0 Y0 X1 Y1 (or --scribble/--mask) to make masks")
    print(f"next: coin-cl run {args.out}")
    return 0
