"""argparse `type=` functions for the CLI's plain values: each turns a string into the value or
raises `argparse.ArgumentTypeError`, which argparse prints as one line naming the flag and the
value (exit code 2). Values a config dataclass holds are checked again in its `__post_init__`."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def folder(text: str) -> Path:
    """A folder to write: a non-empty path (an empty one would mean the current directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a folder name: give the folder to write, e.g. runs/room"
        )
    return Path(text)


def scale_or_capture(text: str) -> float | str:
    """A finite number > 0, or "capture"."""
    return "capture" if text == "capture" else positive_float(text)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a positive number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number; give one > 0")
    return v


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a number >= 0") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} is negative or not finite; give a number >= 0")
    return v


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number; give one >= 1") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is below 1; give a step count >= 1")
    return v


def existing_file(text: str) -> str:
    """The path of a file that exists."""
    if not text.strip() or not Path(text).expanduser().is_file():
        raise argparse.ArgumentTypeError(f"{text!r}: no such file; check the path")
    return text
