"""The CPU kernels' frames: a kernel call's loop over its blocks and save intervals, around a method family's save
interval (ensemble.engine.runge_kutta) or an adaptive pair's trial steps (ensemble.engine.adaptive). A kernel's
file (ensemble.engine.kernels) calls `fixed_step` or `adaptive` with the scene's functions and the method's data;
Numba inlines it, so that the block size, the tableau and the scene's functions are constants of the one loop nest
LLVM compiles.
"""
from __future__ import annotations

from numba import njit

from .adaptive import trial_sweep
from .blocks import (
    FAST,
    H,
    block_done,
    cache_line_array,
    check_members,
    copy_into,
    counts_out,
    state_accept,
    state_load,
    state_saved,
    state_start,
    trial_steps,
)
from .control import control_step
from .tuples import converted, loaded, stored


@njit(inline="always", **FAST)
def fixed_step(interval, like_y, like_p, B, state0, rate, h, steps_per_save, limit, samples, status, failure_time,
               progress, works, start, first_block, end_block, begin, remember, steps, events):
    """Blocks first_block .. end_block - 1 from sample `start` on (0: from state0 and rate; later: from where the
    last call left works) through samples.shape[1] save intervals of steps_per_save steps of h (s) each.

    interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context) takes a block's work array
    through save interval i (a family's members_interval: ensemble.engine.runge_kutta, .splitting), its events
    watched by remember and steps; like_y and like_p are tuples of D and P values (their lengths matter). begin,
    remember, steps: ensemble.engine.events's (NO_BEGIN, NO_REMEMBER, NO_STEPS for a kernel without events),
    events its arrays (or ()), context (events, status, failure_time, j0)."""
    D, P = len(like_y), len(like_p)
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        j0 = block * B
        context = (events, status, failure_time, j0)
        copy_into(work, works[block])
        if start == 0:
            state_load(work, state0, rate, block, samples, D, P, B)
            check_members(work, 0, D, B, j0, limit, status, failure_time, 0.0)  # a non-finite start
            begin(like_y, like_p, work, B, context)
        elif block_done(samples, status, progress, block, B):
            continue
        for i in range(max(start, 1), start + samples.shape[1]):
            interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context)
            if state_saved(work, samples, i - start, block, limit, status, failure_time, progress,
                           i * steps_per_save * h, -1, D, B):
                break
        copy_into(works[block], work)


@njit(inline="always", **FAST)
def adaptive(rhs, pair, stage_loop, controller, like_y, like_p, B, state0, rate, control, save_dt, limit, samples,
             counts, status, failure_time, progress, works, start, first_block, end_block, begin, levels_of, watch,
             events):
    """fixed_step for an embedded pair (ensemble.engine.adaptive): each member steps to each saved time i save_dt
    (s) in steps of its own, accepted or rejected by control.control_step (controller: alpha, beta, safety,
    min_factor, max_factor); control (3, members): first step (0: Hairer's guess), rtol, atol; counts (3,
    members): the accepted and rejected steps and the rhs evaluations so far. begin, events: as fixed_step's;
    levels_of(context), the events' levels, once per block; watch(like_y, like_p, work, B, K, NEW, C0, S, levels,
    context) after each step's control (ensemble.engine.events.adaptive_watcher, or NO_LEVELS, NO_ADAPTIVE_WATCH).

    Work rows: state (D), parameters (P), the stages' slopes from K (D each), the trial state from NEW, the
    control block from C0 (blocks.CONTROL_ROWS)."""
    alpha, beta, safety, min_factor, max_factor = controller
    D, P, S = len(like_y), len(like_p), len(pair[0])
    K = D + P
    NEW = K + D * S
    C0 = NEW + D
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        j0 = block * B
        context = (events, status, failure_time, j0)
        levels = levels_of(context)
        copy_into(work, works[block])
        if start == 0:
            state_load(work, state0, rate, block, samples, D, P, B)
            begin(like_y, like_p, work, B, context)
            for j in range(B):
                y, p = loaded(work, 0, B, j, like_y), loaded(work, D, B, j, like_p)
                stored(work, K, B, j, converted(rhs(0.0, *y, *p), y))
                state_start(work, control, K, C0, B, j, j0, D, save_dt)
            check_members(work, 0, D, B, j0, limit, status, failure_time, 0.0, C0 + H)  # a non-finite start
        elif block_done(samples, status, progress, block, B):
            continue
        for i in range(max(start, 1), start + samples.shape[1]):
            target = i * save_dt
            while trial_steps(work, C0, B, target):
                trial_sweep(rhs, pair, stage_loop, like_y, like_p, work, B, K, NEW, C0)
                control_step(work, C0, B, target, j0, status, failure_time, S - 1, alpha, beta, safety, min_factor,
                             max_factor)
                watch(like_y, like_p, work, B, K, NEW, C0, S, levels, context)
                state_accept(work, K, NEW, C0, S, D, B)
            if state_saved(work, samples, i - start, block, limit, status, failure_time, progress, target, C0 + H,
                           D, B):
                break
        counts_out(work, C0, B, counts, j0)
        copy_into(works[block], work)
