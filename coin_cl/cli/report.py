"""`coin-cl report`: rebuild a run's page, OUT/report.html (a thin parser over
`coin_cl.report_html.write_report`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="(re)write RUN/report.html: the run's page to open in a browser")
    p.add_argument("run", type=Path, help="a coin-cl run folder (the --out of coin-cl run)")
    p.set_defaults(func=cmd_report)


def cmd_report(args: argparse.Namespace) -> int:
    from coin_cl.cli.guard import output_folder
    from coin_cl.report_html import write_report

    if not args.run.is_dir():
        raise FileNotFoundError(
            f"{args.run} is not a coin-cl run folder (no such folder): give the --out of a coin-cl run"
        )
    with output_folder(args.run, "run"):  # a run's own folder, locked, links refused
        page = write_report(args.run)
    print(f"wrote {page}")
    return 0
