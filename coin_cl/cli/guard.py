"""The output folder of a CLI command: checked (`coin_cl.outdir`), locked
(`coin_cl.pipeline.lock`), marked and confined (`coin_cl.atomic.confined_to`) before the command
writes anything in it."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

# What an interrupted command leaves, for its one-line message (coin_cl.cli.main).
KEPT = {
    "run": "finished stages are kept in {out}",
    "train": "the last checkpoint is kept in {out}",
    "prepare": "finished steps are kept in {out}",
    "demo": "finished parts are kept in {out}",
}


@contextmanager
def output_folder(
    out: str | Path, command: str, ignore: Iterable[str] = (), adopt: bool = False
) -> Iterator[Path]:
    """`with output_folder(OUT, "run"):` the block runs holding OUT's lock, with OUT marked as
    `command`'s and every atomic write under it refusing links. Refused (one line, nothing written)
    when OUT is neither new, empty nor `command`'s (`adopt`: a non-empty unmarked folder is taken),
    when another command holds it, or when a symbolic link lies anywhere in it (outside `ignore`)."""
    from coin_cl.atomic import confined_to, refuse_links
    from coin_cl.outdir import MARKER, check_output, mark_output
    from coin_cl.pipeline.lock import LOCK_NAME, command_lock

    out = Path(out)
    ignore = tuple(ignore)
    new = check_output(out, command, ignore, adopt) == "new"
    locked = False
    try:
        with command_lock(out):
            locked = True
            check_output(out, command, ignore, adopt)  # again, now that no other command can write it
            refuse_links(out, ignore)  # a planted link: what the command clears or writes must be its own
            mark_output(out, command)
            with confined_to(out):
                yield out
    except BaseException:
        # refused or stopped before writing anything: the folder it made goes again
        if locked and new and out.is_dir() and {p.name for p in out.iterdir()} <= {MARKER, LOCK_NAME}:
            (out / MARKER).unlink(missing_ok=True)
            out.rmdir()
        raise


def interrupted_message(command: str, out: Path | None) -> str:
    """The one line of a Ctrl-C: what was kept and how to go on."""
    if out is None:
        return f"coin-cl {command}: interrupted"
    kept = KEPT.get(command, "what was finished is kept in {out}").format(out=out)
    return f"coin-cl {command}: interrupted; {kept}; run the same command again to resume"
