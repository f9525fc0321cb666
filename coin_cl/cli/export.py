"""`coin-cl export`: a run's Gaussians as a file other tools open (a thin parser over
`coin_cl.gs.export.export_run`; docs/EXPORT.md)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export", help="a run's Gaussians as a 3DGS PLY, a graphdeco output folder or a .splat"
    )
    p.add_argument("source", type=Path, help="a coin-cl run folder (its eval/point_cloud.ply) or a 3DGS PLY")
    p.add_argument("--format", choices=("ply", "graphdeco", "splat"), default="ply",
                   help="ply: 3DGS PLY (SIBR, SuperSplat, gsplat); graphdeco: a folder as graphdeco's "
                        "train.py writes (point_cloud/iteration_N/point_cloud.ply, cameras.json, "
                        "cfg_args); splat: antimatter15's 32-byte .splat (web viewers)")  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="file to write (a folder for graphdeco)")
    p.add_argument("--sh-degree", type=int, default=3, choices=(0, 1, 2, 3),
                   help="ply: SH degree of the record, zero-padded (default 3: SIBR's record)")  # fmt: skip
    p.add_argument("--iteration", type=int, default=30_000,
                   help="graphdeco: the N of point_cloud/iteration_N (default 30000)")  # fmt: skip
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from coin_cl.gs.export import export_run

    out, n, dropped = export_run(args.source, args.format, args.out, sh_degree=args.sh_degree,
                                 iteration=args.iteration)  # fmt: skip
    extra = f" ({dropped} holding NaN/Inf left out)" if dropped else ""
    print(f"wrote {n} Gaussians as {args.format} to {out}{extra}")
    return 0
