"""Reading checkpoints: the one way coin-cl loads a `torch.save` file, safe for a file from anyone.

A `torch.save` file is a pickle, and unpickling may call any function the file names. Every
checkpoint coin-cl writes (the GS trainer's ckpt.pt, the scene prior's cache and its training
checkpoint) holds only tensors, numbers, strings, None and lists / tuples / dicts of them, so
`load_checkpoint` reads with `torch.load(weights_only=True)` and no allow-list: torch's restricted
unpickler builds exactly those and refuses any other global before anything is called. A run
folder, a training folder or a cached prior received from someone else can therefore be read
without running its code.

Whatever goes wrong comes out as one `CheckpointError` (a ValueError, so the CLI prints it as one
line) naming the file and what to do: a file that is not a whole torch.save file (truncated, empty,
random bytes, a bare pickle: told before anything is unpickled), a file that asks for anything else
("refused"; nothing in it is run), a damaged archive, a file that does not hold a dict. Imports
torch and nothing of coin_cl, so every layer (diffusion/ included) may use it.
"""

from __future__ import annotations

import os
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

# What to do with a bad checkpoint when the caller names nothing better.
DEFAULT_REMEDY = "delete it and rerun the step that writes it"
# The global torch's restricted unpickler refused, from its message.
_GLOBAL = re.compile(r"GLOBAL ([\w.]+)")
# The first bytes of a torch.save file in the format before torch 1.6 (a pickled magic number).
_LEGACY_MAGIC = b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19"
_MAX_REASON = 160  # characters of the library's own message kept in ours


class CheckpointError(ValueError):
    """A checkpoint that cannot be read safely: refused (it asks to run or build something no
    coin-cl checkpoint holds), truncated or corrupt, or not a dict. The message is one line naming
    the file and what to do."""


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split("\n", 1)[0].split()) or type(exc).__name__
    return text if len(text) <= _MAX_REASON else text[: _MAX_REASON - 3] + "..."


def load_checkpoint(
    path: str | os.PathLike, remedy: str = DEFAULT_REMEDY, what: str = "coin-cl checkpoint"
) -> dict[str, Any]:
    """The dict `torch.save` wrote to `path`, tensors on the CPU, read without running code.

    path: the file; remedy: what the user should do with a bad one (ends the message, e.g.
    "rerun with --force 2_refgs"); what: what the file should be, for messages ("coin-cl
    checkpoint", "DINO weight file"). Raises CheckpointError for a refused, truncated, corrupt or
    non-dict file; OSError (FileNotFoundError, PermissionError, ...) when the file cannot be opened.
    """
    import torch

    path = Path(path)
    ours = what == "coin-cl checkpoint"
    with open(path, "rb") as fh:  # OSError here names the file itself
        # torch.save writes a zip archive (its directory at the end) or, before torch 1.6, a pickle
        # stream opening with a magic number: a truncated or empty file, random bytes or a bare
        # pickle are told apart before anything is unpickled.
        legacy = fh.read(len(_LEGACY_MAGIC)) == _LEGACY_MAGIC
        fh.seek(0)
        if not legacy and not zipfile.is_zipfile(fh):
            raise CheckpointError(
                f"{path} is not a complete {what} (a torch.save file): it is truncated, empty or "
                f"another kind of file; {remedy}"
            )
        fh.seek(0)
        try:
            state = torch.load(fh, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError as exc:
            m = _GLOBAL.search(str(exc))
            if m is None:  # an opcode no torch.save writes: damaged bytes or a hand-made pickle
                raise CheckpointError(
                    f"{path} is a corrupt {what} (its pickle holds instructions torch.save never "
                    f"writes); nothing in it was run; {remedy}"
                ) from None
            origin = " (it was not written by coin-cl, or by an older version)" if ours else ""
            raise CheckpointError(
                f"{path} was refused: it asks to run or build {m.group(1)}, which no {what} "
                f"holds{origin}; nothing in it was run; {remedy}"
            ) from None
        except Exception as exc:  # zip, EOF, size and storage errors of a damaged file
            raise CheckpointError(f"{path} is a corrupt {what} ({_first_line(exc)}); {remedy}") from None
    if not isinstance(state, dict):
        raise CheckpointError(
            f"{path} does not hold a state_dict or checkpoint dict (it holds a "
            f"{type(state).__name__}); {remedy}"
        )
    return state


def malformed(path: str | os.PathLike, exc: BaseException, remedy: str = DEFAULT_REMEDY) -> CheckpointError:
    """The one-line error for a checkpoint that loaded but lacks what its reader needs (`exc`: the
    KeyError / TypeError its reader met), e.g. a dict saved by another program."""
    return CheckpointError(
        f"{Path(path)} is not the checkpoint expected here ({type(exc).__name__}: "
        f"{_first_line(exc)}); {remedy}"
    )
