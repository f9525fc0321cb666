"""Which folders a command may write in: the one rule for every `--out`.

A command (`run`, `train`, `prepare`, `demo`, `make-scene`, `eval`, `render --out`) writes only in
an output folder that is absent (it creates it), empty, or carries its own marker `OUT/.coin-cl-out`
(JSON: the command that made it and when), written when the command takes the folder. A non-empty
folder without the marker is refused with one line (`OutputFolderError`): coin-cl deletes or renames
only what it wrote, so it must know the folder is its own. Folders that earlier versions made before
the marker existed are recognised by a file only that command writes (`LEGACY`: a run's run.json, a
training's ckpt.pt, ...) and get the marker then. `render` without `--out` writes in the train or
run folder it renders, under that command's rule (its marker or LEGACY file, its lock).

Only pure-stdlib imports (`coin_cl.atomic`), like the lock it is taken with.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from pathlib import Path

from coin_cl.atomic import write_text

MARKER = ".coin-cl-out"
LOCK_NAME = ".coin-cl.lock"  # coin_cl.pipeline.lock's, not content: the folder is still empty

# Files that identify a folder a command wrote before the marker existed.
LEGACY: dict[str, tuple[str, ...]] = {
    "run": ("run.json", "plan.json"),
    "train": ("ckpt.pt", "cameras.json"),
    "prepare": (".prepare", "prepare_report.json"),
    "demo": ("demo.json",),
    "make-scene": ("views.txt",),
    "eval": ("metrics.json",),
}


class OutputFolderError(ValueError):
    """An output folder the command may not write in; the message names it and what to do."""


def read_marker(out: Path) -> dict | None:
    """The marker's content, or None when `out` has none (a link is not a marker)."""
    m = Path(out) / MARKER
    if m.is_symlink() or not m.is_file():
        return None
    try:
        doc = json.loads(m.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"command": None}
    return doc if isinstance(doc, dict) else {"command": None}


def check_output(out: str | Path, command: str, ignore: Iterable[str] = (), adopt: bool = False) -> str:
    """Whether `command` may write in `out`: "new" (absent), "empty", "ours" (its marker or a
    LEGACY file), "adopted" (non-empty, unmarked, and `adopt`: the user said so, `prepare
    --replace`); raises `OutputFolderError` otherwise (another command's marker always). `ignore`:
    names inside `out` that do not count as content (the photos' folder when --out is its parent)."""
    out = Path(out)
    if not out.exists() and not out.is_symlink():
        return "new"
    if not out.is_dir():
        raise OutputFolderError(f"--out {out} is a file, not a folder: give a new or empty folder")
    mark = read_marker(out)
    if mark is not None:
        made_by = mark.get("command")
        if made_by != command:
            raise OutputFolderError(
                f"{out} is the output folder of coin-cl {made_by or '(unknown)'}, not of coin-cl "
                f"{command}: give {command} another --out (a new or empty folder)"
            )
        return "ours"
    skip = {LOCK_NAME, *ignore} | ({MARKER} if not (out / MARKER).is_symlink() else set())
    content = [p.name for p in out.iterdir() if p.name not in skip]
    if not content:
        return "empty"
    if any((out / name).exists() for name in LEGACY.get(command, ())):
        return "ours"
    if adopt:
        return "adopted"
    raise OutputFolderError(
        f"{out} is not empty and is not a coin-cl {command} folder (no {MARKER} in it): give a new or "
        "empty folder as --out (coin-cl writes and deletes only in folders it made)"
    )


def mark_output(out: str | Path, command: str) -> None:
    """Write `out`'s marker for `command` (kept when already there)."""
    out = Path(out)
    if read_marker(out) is None:
        doc = {"command": command, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        write_text(out / MARKER, json.dumps(doc) + "\n")
