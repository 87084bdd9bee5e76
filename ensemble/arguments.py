"""The command line's conventions, shared by `ensemble` and the benchmark tools: one-line errors, exit statuses."""
from __future__ import annotations

import argparse

from .errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK  # noqa: F401


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block) and exit status 2."""

    def error(self, message):
        program, _, where = self.prog.partition(" ")
        self.exit(EXIT_BAD_INPUT, f"{program}: error: {where + ': ' if where else ''}{message} "
                                  f"(see {self.prog} --help)\n")


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = float(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def location(text: str):
    """An argparse type: a path, or an fsspec URL of a Zarr store (ensemble.places.place)."""
    from .errors import EnsembleError
    from .places import place

    try:
        return place(text)
    except EnsembleError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
