"""The command line's conventions, shared by `ensemble` and the analysis scripts: one-line errors, exit statuses."""
from __future__ import annotations

import argparse

EXIT_BAD_INPUT = 2  # bad input: nothing was run, nothing written
EXIT_FAILED = 3  # the run failed midway (a full disk, chunks failing on a cluster): its parts stay for --resume
EXIT_INTERRUPTED = 130  # Ctrl-C


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
