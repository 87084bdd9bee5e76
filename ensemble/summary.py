"""What a run did: its summary line, and the tally of what this invocation computed."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .results import Status

ANNOUNCE_AFTER = 1.0  # s: kernels taking longer than this to get ready are being compiled, and a line says so


@dataclass(frozen=True)
class Summary:
    members: int
    member_steps: int
    seconds: float
    steps_each: int | None = None  # when every member took the same number of steps
    blew_up: int = 0  # failed members (status BLEW_UP)
    underflowed: int = 0  # failed members (status STEP_SIZE_UNDERFLOW)
    stopped: int = 0  # members stopped at an event (status STOPPED_BY_EVENT): not failures
    closed_form: bool = False  # every member was evaluated in closed form (no steps)
    preparing: float = 0.0  # seconds spent compiling or loading kernels before the run, not in `seconds`
    resumed: int = 0  # members of the result computed by an earlier, interrupted run (not counted above)
    complete_already: bool = False  # an earlier run made the result whole and was stopped before removing its parts

    def __str__(self) -> str:
        failed = self.blew_up + self.underflowed
        failures = (f"; {failed} of {_members(self.members + self.resumed)} failed ({self.blew_up} blew up, "
                    f"{self.underflowed} step size underflow)" if failed else "")
        failures += f"; {self.stopped} stopped at events" if self.stopped else ""
        if self.complete_already:
            return (f"complete already ({_members(self.resumed)}): the run that made it was stopped before removing "
                    f"its parts, which are removed now")
        if not self.members:
            return f"{_members(self.resumed)} from an earlier run's parts, assembled in {self.seconds:.3g} s" + failures
        if self.closed_form:
            return f"{_members(self.members)} (closed form) in {self.seconds:.3g} s" + failures
        rate = self.member_steps / self.seconds if self.seconds > 0 else float("inf")
        steps = (f"{_members(self.members)} x {self.steps_each} steps" if self.steps_each is not None
                 else f"{_members(self.members)}, {self.member_steps} member-steps")
        compiling = f" (after {self.preparing:.3g} s compiling kernels)" if self.preparing > ANNOUNCE_AFTER else ""
        resumed = f" ({self.resumed} more from the parts of an earlier run)" if self.resumed else ""
        return f"{steps} in {self.seconds:.3g} s: {rate:.3g} member-steps/s" + compiling + resumed + failures


def _members(count: int) -> str:
    return f"{count} member" if count == 1 else f"{count} members"


@dataclass
class Tally:
    """What this invocation of a run computed: members, member-steps, the distinct step counts."""
    members: int = 0
    member_steps: int = 0
    step_counts: set = field(default_factory=set)

    def add(self, records: dict[str, np.ndarray]) -> None:
        self.merge(counts(records))

    def merge(self, counts: dict) -> None:
        """Add what counts() counted (here, or in a receipt: ensemble.zarr_store.Region.receipt)."""
        self.members += counts["members"]
        self.member_steps += counts["member_steps"]
        self.step_counts.update(counts["step_counts"])


def counts(records: dict[str, np.ndarray]) -> dict:
    """What the summary needs of a range's records: its members, member-steps, distinct step counts, and how many
    members ended in each Status (JSON-ready)."""
    steps = records["steps_accepted"] + records["steps_rejected"]
    status = np.bincount(records["status"].astype(np.int64), minlength=len(Status))
    return {"members": len(steps), "member_steps": int(steps.sum()), "step_counts": np.unique(steps).tolist(),
            "status": status.tolist()}
