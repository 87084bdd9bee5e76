"""What a kernel reports per member: the contract between the kernels, the runner, the store and the analysis.

One definition each of: a member's status and what it means, the rows of the
step counts, the sentinels the adaptive step control leaves, the default
blow-up factor, the events a run asks for, and the Outcome a launch returns.
"""
from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np


class Status(IntEnum):
    """How a member ended (the dataset's `status`, a CF flag variable)."""

    OK = 0  # ran to t_end
    BLEW_UP = 1  # its state was not finite, or outgrew blowup_factor times its start
    STEP_SIZE_UNDERFLOW = 2  # an adaptive method's step shrank below 1e-14 of the time it was heading for
    STOPPED_BY_EVENT = 3  # an event that stops its member occurred (not a failure: its state there is kept)

    @classmethod
    def flag_values(cls) -> np.ndarray:
        return np.array([s.value for s in cls], dtype=np.int8)

    @classmethod
    def flag_meanings(cls) -> str:
        """CF flag_meanings: the names in order of value, e.g. "ok blew_up step_size_underflow"."""
        return " ".join(s.name.lower() for s in cls)


#: Rows of a launch's per-member step counts (3, members), and the dataset variables that record them.
COUNTS = ("steps_accepted", "steps_rejected", "rhs_evals")
ACCEPTED, REJECTED, RHS_EVALS = range(len(COUNTS))

#: What the adaptive step control leaves in a member's error row after a trial step, besides an error norm >= 0.
NO_STEP = -1.0  # the member had no step to take (it is at the saved time, or stopped)
UNDERFLOWED = -2.0  # the member's step size underflowed: it stops

#: A member fails when a component of its state outgrows its largest component at the start this many times.
DEFAULT_BLOWUP_FACTOR = 1e6


class Event(NamedTuple):
    """An event a run asks for (its run file's [events.<name>]): when `of` (a state variable, observable or the
    scene's event function, its value `index` of a vector) crosses `level`."""

    name: str
    of: str
    index: int  # -1: a scalar
    source: tuple  # the kernel's value of it: ("state", row) or ("function", scene function, index[, its watch])
    level: float = 0.0
    direction: str = "both"  # "up", "down" or "both"
    count: int = 1  # occurrences kept per member
    stop: bool = False  # the member stops at its first occurrence
    keep: tuple = ()  # saved variables kept at each kept occurrence (<name>_<variable>)

    @property
    def sign(self) -> float:
        """The kernels' direction: +1 up, -1 down, 0 both."""
        return {"up": 1.0, "down": -1.0, "both": 0.0}[self.direction]


class Outcome(NamedTuple):
    """What a launch did, per member (the last axis)."""

    samples: np.ndarray  # (n_save, state, members); NaN from the first saved time at which a member had failed
    counts: np.ndarray  # (3, members) int64, rows COUNTS: steps accepted, steps rejected, rhs evaluations
    status: np.ndarray  # (members,) int8: Status values
    failure_time: np.ndarray  # (members,) s: saved time at which a failure was seen (step time for an underflow)
    event_times: np.ndarray | None = None  # (events, count, members) s: kept occurrences, NaN where fewer
    event_counts: np.ndarray | None = None  # (events, members) int64: every occurrence
    stopped: np.ndarray | None = None  # (state, members): a member's state at the event that stopped it, else NaN
    event_states: np.ndarray | None = None  # (events, count, state, members): states at kept occurrences (see
    # launch.event_states), NaN where none
