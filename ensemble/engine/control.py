"""The adaptive pairs' step-size control, written once for both devices: `controlled` chooses one member's next
step after its trial step; the CPU kernels sweep it over a block's members (`control_step`), a CUDA thread calls
it for its member (ensemble.engine.gpu, which compiles it as a device function with the GPU's own log2 and exp2).

An accepted step's next is h clip(safety err^-alpha err_previous^beta, min_factor, max_factor), at most h after a
rejection; a rejected one's h max(min_factor, safety err^-alpha) (min_factor when err is not finite). A trial
step whose error is not a number is rejected like one with a large error.
"""
from __future__ import annotations

from numba import njit

from ..results import ACCEPTED, NO_STEP, REJECTED, RHS_EVALS, UNDERFLOWED
from .blocks import (
    COUNTED,
    ERR,
    FAST,
    FIRST_LOG2_ERR_PREVIOUS,
    LOG2_ERR_PREVIOUS,
    REJECTED_LAST,
    STEP,
    TIME,
    UNDERFLOW,
    H,
    exp2_of,
    finite,
    log2_positive,
    select,
)


@njit(inline="always", **FAST)
def controlled(err, step, h, log2_previous, rejected_last, time, target, alpha, beta, safety, min_factor,
               max_factor):
    """One member's control after a trial step of size step > 0 (s) from `time` towards the saved time `target`
    (s), with error norm err; h is the step before clipping to land on target, log2_previous the log2 of the last
    accepted step's error, rejected_last whether the last trial step was rejected. Returns (accepted, underflowed,
    next h, log2 of the error to remember, time after).

    In selects (`select`, &), not branches: inlined into a loop over a block's members, it vectorizes. With a branch
    per member and libm's pow, a top's dopri5 step cost 31.5 times its rk4 step; with selects 8.8 to 9 times."""
    usable = finite(err)
    usable_err = select(usable, err, 1.0e300)
    accepted = usable_err <= 1.0
    log2_err = log2_positive(max(usable_err, 1e-10))
    factor = safety * exp2_of(-alpha * log2_err + select(accepted, beta * log2_previous, 0.0))
    accepted_factor = min(max_factor, max(min_factor, select(rejected_last, min(factor, 1.0), factor)))
    factor = select(accepted, accepted_factor, select(usable, max(min_factor, factor), min_factor))
    landed = step >= target - time  # a step clipped to land on the saved time does not shrink the next one
    rejected_h = step * factor
    underflowed = (not accepted) & (rejected_h <= 1e-14 * target)  # the step underflowed: the member gives up
    next_h = select(accepted, max(step * factor, select(landed, h, 0.0)), select(underflowed, 0.0, rejected_h))
    return (accepted, underflowed, next_h, select(accepted, max(log2_err, FIRST_LOG2_ERR_PREVIOUS), log2_previous),
            select(accepted, select(landed, target, time + step), time))


@njit(inline="always", **FAST)
def counted(err, step, h, log2_previous, rejected_last, time, target, counts, evaluations, controller):
    """`controlled` for one member (the CUDA kernels'), controller its (alpha, beta, safety, min_factor,
    max_factor), and its counts (accepted steps, rejected steps, right-hand-side evaluations) after a trial step
    of `evaluations` evaluations: (accepted, underflowed, next h, log2 of the error to remember, time after,
    counts)."""
    alpha, beta, safety, min_factor, max_factor = controller
    accepted, underflowed, next_h, log2_err, time = controlled(err, step, h, log2_previous, rejected_last, time,
                                                               target, alpha, beta, safety, min_factor, max_factor)
    accepted_count, rejected_count, evaluated = counts
    return (accepted, underflowed, next_h, log2_err, time,
            (accepted_count + accepted, rejected_count + (not accepted), evaluated + evaluations))


@njit(inline="always", **FAST)
def control_step(work, c0, B, target, j0, status, failure_time, new_stages, alpha, beta, safety, min_factor,
                 max_factor):
    """After a trial step of every member in a block (control rows from c0: blocks.H ..): `controlled` for each
    member that had a step to take. A trial step costs `new_stages` right-hand-side evaluations (an FSAL pair
    reuses its last stage).

    Afterwards ERR is NO_STEP for members that had no step to take, UNDERFLOWED for members whose step
    underflowed (they stop: H = 0, status UNDERFLOW at their time), and REJECTED_LAST is 0 for members whose step
    was accepted; the caller moves those to their new state. Every value is loaded up front and every row stored,
    since a load or store under a condition becomes a masked one (vmaskmovpd, slow on AMD Zen 3)."""
    underflows = 0
    for j in range(B):
        step, err = work[(c0 + STEP) * B + j], work[(c0 + ERR) * B + j]
        time, h = work[(c0 + TIME) * B + j], work[(c0 + H) * B + j]
        log2_previous, rejected_last = work[(c0 + LOG2_ERR_PREVIOUS) * B + j], work[(c0 + REJECTED_LAST) * B + j]
        moving = step > 0.0
        accepted, underflowed, next_h, log2_next, next_time = controlled(
            err, step, h, log2_previous, rejected_last > 0.0, time, target, alpha, beta, safety, min_factor,
            max_factor)
        accepted, underflowed = moving & accepted, moving & underflowed
        underflows += underflowed
        work[(c0 + TIME) * B + j] = select(moving, next_time, time)
        work[(c0 + H) * B + j] = select(moving, next_h, h)
        work[(c0 + LOG2_ERR_PREVIOUS) * B + j] = select(moving, log2_next, log2_previous)
        work[(c0 + REJECTED_LAST) * B + j] = select(moving, select(accepted, 0.0, 1.0), rejected_last)
        work[(c0 + ERR) * B + j] = select(moving, select(underflowed, UNDERFLOWED, err), NO_STEP)
    _count_steps(work, c0, B, j0, status, failure_time, new_stages, underflows)


@njit(inline="always", **FAST)
def _count_steps(work, c0, B, j0, status, failure_time, new_stages, underflows):
    """control_step's counts, into the block's COUNTED rows (blocks.counts_out hands them on), and its failures,
    from the rows it wrote. Loops of their own: inside its loop they kept it from vectorizing. Counting straight
    into the `counts` array kept this loop scalar, a sixth of a top's dopri5 step."""
    for j in range(B):
        moving = work[(c0 + ERR) * B + j] != NO_STEP
        accepted = moving & (work[(c0 + REJECTED_LAST) * B + j] == 0.0)
        work[(c0 + COUNTED + ACCEPTED) * B + j] += select(accepted, 1.0, 0.0)
        work[(c0 + COUNTED + REJECTED) * B + j] += select(moving & (not accepted), 1.0, 0.0)
        work[(c0 + COUNTED + RHS_EVALS) * B + j] += select(moving, new_stages, 0.0)
    if underflows:
        for j in range(B):
            if work[(c0 + ERR) * B + j] == UNDERFLOWED:
                status[j0 + j] = UNDERFLOW
                failure_time[j0 + j] = work[(c0 + TIME) * B + j]
