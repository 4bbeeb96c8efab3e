"""Command-line pieces shared by every parser: the option types and the one-line parser.

Used by :mod:`.cli` (``python -m dancing_points_addon``), by :mod:`.batch` (its
options, shared by the ``batch`` subcommand and Blender's ``convert`` command)
and by the Blender side's ``convert`` command. Imports nothing of the package
but :mod:`.errors`, so that any of them can import it.
"""
from __future__ import annotations

import argparse
import math

from .errors import UserError


class UsageError(UserError):
    """A bad command line (reported like bad input: one line, exit 2)."""


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are a :class:`UsageError`
    (one line) instead of the usage text and ``SystemExit``."""

    def error(self, message):  # argparse would print the usage too: keep it one line
        raise UsageError(f"{self.prog}: {message}")


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return v


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return v


def height_metres(text: str) -> float:
    v = positive_float(text)
    if not 0.5 <= v <= 3.0:
        raise argparse.ArgumentTypeError(f"must be a height in metres between 0.5 and 3.0, got {text!r}")
    return v
