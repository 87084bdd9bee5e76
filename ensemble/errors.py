"""The one root of ensemble's errors and the one table of exit statuses.

Every error ensemble raises about its input or its run derives from EnsembleError and says in one line what is
wrong and where; its `exit_status` is the status `ensemble` exits with for it.

| status | meaning |
|---|---|
| 0 | done (members that blew up are counted in the summary, not an error) |
| 1 | a fit's --check found results that disagree with the theory |
| 2 | bad input: nothing was run, nothing written |
| 3 | the run started and failed midway (a full disk, chunks that kept failing on a cluster): its finished chunks
      stay for --resume |
| 130 | interrupted (Ctrl-C): the finished chunks stay for --resume |
"""
from __future__ import annotations

EXIT_OK = 0
EXIT_CHECK_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_FAILED = 3
EXIT_INTERRUPTED = 130


class EnsembleError(Exception):
    """An error in ensemble's input or run, with a one-line message; exit_status is what the command exits with."""

    exit_status = EXIT_BAD_INPUT


class Incomplete(EnsembleError):
    """Some members could not be computed (their chunks kept failing on the cluster); the others are in parts."""

    exit_status = EXIT_FAILED

    def __init__(self, ranges: list[tuple[int, int]], cause: str):
        self.ranges, self.cause = ranges, cause
        members = ", ".join(f"{a}..{b - 1}" if b - a > 1 else str(a) for a, b in ranges)
        super().__init__(f"members {members} were not computed ({cause})")


class DeviceUnavailable(EnsembleError):
    """A run asks for a device this machine lacks (device = "cuda" without a GPU or without numba-cuda)."""
