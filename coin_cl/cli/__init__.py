"""The `coin-cl` command line: thin parsers over the Python API (`coin_cl.demo`, `coin_cl.evaluation`,
`coin_cl.gs.trainer`, `coin_cl.gs.model_kinds`, `coin_cl.gs.export`, `coin_cl.prepare`,
`coin_cl.render_utils`, `coin_cl.report_html`, `coin_cl.scene`).

A module of this package joins the CLI by defining `add_commands(subparsers)`; the list below names
them. Nothing outside `coin_cl.cli` imports it.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Modules that register subcommands. A module that is missing is skipped with a log line, so a
# partial checkout still gives a working CLI for what is there.
COMMAND_MODULES = [
    "coin_cl.cli.engine",  # demo, doctor
    "coin_cl.cli.scene",  # make-scene, eval
    "coin_cl.cli.train",  # train, render
    "coin_cl.cli.run",  # run (CoIn end to end)
    "coin_cl.cli.report",  # report (a run's page, report.html)
    "coin_cl.cli.prepare",  # prepare (photos -> posed scene + masks)
    "coin_cl.cli.export",  # export (a run's Gaussians as ply / graphdeco / splat)
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coin-cl", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            logging.getLogger(__name__).debug("CLI module %s not present", name)
            continue
        mod.add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        # Ctrl-C: every write is atomic and the lock is released on the way out, so a rerun resumes;
        # one line says so (no traceback). 130 = 128 + SIGINT, as a shell reports it.
        if args.verbose:
            raise
        from coin_cl.cli.guard import interrupted_message

        out = getattr(args, "out", None) or getattr(args, "out_dir", None)
        print("\n" + interrupted_message(args.command, out), file=sys.stderr)
        return 130
    except (OSError, ValueError, RuntimeError) as exc:
        # User-facing failures carry a message naming the file or value (OSError: a file the
        # system refused, a full or read-only disk); no traceback needed. One line, always.
        if args.verbose:
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__
        print(f"coin-cl {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
