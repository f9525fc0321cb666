"""The one weight rule of `coin_cl.nets`: an environment variable names a local file; nothing is ever
downloaded and nothing runs with random weights.

A network declares its file with a `WeightFile` (the variable and what file it expects). Unset, the
network is unavailable and callers report `unavailable(...)`; set to a path that is not a file, or to a
file that is not a torch state_dict, loading fails with an error naming the variable (where one was
used), the path and the expected file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class WeightFile:
    """A weight file a network needs: `env` names it, `expected` says which file (for messages)."""

    env: str
    expected: str

    def path(self) -> Path | None:
        """The file $`env` names, or None when the variable is unset or empty. A path that is not a
        file raises FileNotFoundError naming the variable, the path and the expected file."""
        value = os.environ.get(self.env)
        if not value:
            return None
        p = Path(value).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"{self.env}={value}: no such file; expected {self.expected}")
        return p


def unavailable(what: str, *files: WeightFile) -> str:
    """The reason `what` is unavailable: which variables to set to which files."""
    wants = " and ".join(f"{f.env} to {f.expected}" for f in files)
    return f"{what} unavailable: set {wants}; no weights are downloaded"


def load_state_dict(path: str | Path, what: str = "weight file") -> dict:
    """A torch state_dict from a local file (a bare state_dict or a {"state_dict": ...} checkpoint),
    loaded on the CPU without running code (`coin_cl.checkpoint`). Errors name the file."""
    from coin_cl.checkpoint import load_checkpoint

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    sd = load_checkpoint(path, f"point to the {what} itself", what=what)
    if "state_dict" in sd:
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise ValueError(f"{path} does not hold a state_dict")
    return sd
