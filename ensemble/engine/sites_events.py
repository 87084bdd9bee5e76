"""Events on a field of sites (ensemble.engine.sites_kernels's kernels with events): each member's events watched
after every step, their crossings located on the method's own step of that one member (ensemble.engine.events),
and the three families' kernels with events, `<family>_events_kernel`, which run sites_kernels's frames with the
hooks here.

A kernel's file with events holds this module's code after sites_kernels's (sites.source), so both read the names
its header binds; those of events: E events, EVENT_ROWS (each one's work row: X + 1 + k for site k + 1's x, V + k
for its v), FIRST_EVENT (their first work row), VALUES (each one's value on a member's state (x; v):
ensemble.engine.events.values_chain) and FAMILY (whose step LOCATED locates on). As a module, they are bound to
sites_kernels's example, watching site 1's x.
"""
import numpy as np
from numba import njit
from numba.cpython.unsafe.tuple import tuple_setitem

from ensemble.engine.blocks import CONTROL_ROWS, FAST, STEP, TIME, H
from ensemble.engine.events import (
    accepted,
    any_crossed,
    component,
    crossed_each,
    levels_and_directions,
    locator,
    stop_member,
    straddles,
    values_chain,
)
from ensemble.engine.sites import CHECK_STEPS, KICK, set_ghosts, stage_sums
from ensemble.engine.sites_kernels import (
    C0,
    FRACTIONS,
    KV,
    KX,
    PERIODIC,
    SEQUENCE,
    WEIGHTS,
    ZX,
    A,
    B,
    E,
    N,
    S,
    V,
    X,
    adaptive_frame,
    merged,
    no_begin,
    piece,
    pieces_per_step,
    runge_kutta_frame,
    runge_kutta_step,
    site_acceleration,
    slopes,
    splitting_frame,
    stage,
)

# ---------------------------------------------------------------- EXAMPLE: what a kernel file's header binds

FAMILY = "runge_kutta"  # the method's family: which step its events are located on (LOCATED)
EVENT_ROWS, FIRST_EVENT = (X + 1,), C0 + CONTROL_ROWS  # each event's work row, the events' first row
VALUES = values_chain((component(0),))  # each event's value on a member's state (x; v): here site 1's x

# ---------------------------------------------------------------- CODE: copied into a kernel's file with events
# EVENT_ROWS holds each event's work row. A fixed step's kernel runs a save interval's steps in groups of at most
# CHECK_STEPS (`<family>_steps`): before a group, the block's state (rows X + 1 .. V + N - 1) goes to rows CHECK
# (2N + 1); after each of its steps, each event's value goes to that event's TRACE rows (CHECK_STEPS + 1 each: its
# value at the group's start, then after each step); after the group, one pass over those rows finds whether any
# member's event crossed, and only then are the crossings located, member by member and step by step in time, each
# on the method's own step of that member (`advance`: the kernel's arithmetic on a block of one member) from its
# state at the step's start, replayed on a block of one from CHECK. The group's loop of steps is that of the kernel
# without events, with a store after each step: a loop that could stop after any step to locate there cost a
# chain's verlet about five points of its rate, and a copy of the state at every step a third. An adaptive
# kernel needs no rows: its trial state is in rows of its own (ZX, ZV) until `accept`, its step's start still in
# rows X, V. The states go to the event arrays as (x; v), 2N values.
TRACE, CHECK = FIRST_EVENT, FIRST_EVENT + E * (CHECK_STEPS + 1)
LIKE_G = (0.0,) * E


@njit(inline="always", **FAST)
def trace_row(e, k):
    """Event e's TRACE row k: its value at a group's start (k = 0) or after the group's step k."""
    return TRACE + e * (CHECK_STEPS + 1) + k


@njit(inline="always", **FAST)
def member_state(work, first, j, B):
    """Member j's state (x; v) (2N,) from a block of B: site i's x at row first + i, its v at row first + N + 1 + i
    (the layout of rows X + 1 .. V + N - 1, a ghost between)."""
    y = np.empty(2 * N)
    for i in range(N):
        y[i] = work[(first + i) * B + j]
        y[N + i] = work[(first + N + 1 + i) * B + j]
    return y


@njit(inline="always", **FAST)
def member_couplings(work, j):
    """Member j's couplings (left; right) (2N,), from rows CL and CR."""
    p = np.empty(2 * N)
    for i in range(2 * N):
        p[i] = work[(2 * N + 2 + i) * B + j]
    return p


@njit(inline="always", **FAST)
def one_member(y, p):
    """A block of one member with state y (x; v) and couplings p (left; right), in a kernel's rows."""
    one = np.zeros(C0)
    for i in range(N):
        one[X + 1 + i] = y[i]
        one[V + i] = y[N + i]
    for i in range(2 * N):
        one[2 * N + 2 + i] = p[i]
    set_ghosts(one, X, N, 1, PERIODIC)
    return one


@njit(**FAST)
def splitting_advance(t0, h, y0, p):
    """A member's splitting step of h (s) from state y0 (2N,), couplings p: its new state (x; v)."""
    one = one_member(y0, p)
    for e in range(len(SEQUENCE)):
        piece(one, SEQUENCE[e], h * FRACTIONS[e], 1)
    return member_state(one, X + 1, 0, 1)


@njit(**FAST)
def runge_kutta_advance(t0, h, y0, p):
    """As splitting_advance, a step of the tableau A, WEIGHTS."""
    one = one_member(y0, p)
    for s in range(S):
        stage(one, s, A, h, -1, 1)
    for i in range(N):
        dx, dv = stage_sums(one, WEIGHTS, S, KX, KV, i, 0, N, 1)
        one[X + 1 + i] += h * dx
        one[V + i] += h * dv
    return member_state(one, X + 1, 0, 1)


@njit(**FAST)
def adaptive_advance(t0, h, y0, p):
    """As splitting_advance, the pair's trial step of h (its last stage state: FSAL)."""
    one = one_member(y0, p)
    slopes(one, X, V, KX, KV, N, 1)
    for s in range(1, S):
        stage(one, s, A, h, -1, 1)
    return member_state(one, ZX + 1, 0, 1)


@njit(inline="always", **FAST)
def events_begin(work, B, context):
    """The block's events' values at t = 0 into the first of their TRACE rows."""
    for e in range(E):
        for j in range(B):
            work[trace_row(e, 0) * B + j] = work[EVENT_ROWS[e] * B + j]


@njit(inline="always", **FAST)
def checkpoint(work):
    """The block's state (rows X + 1 .. V + N - 1) into rows CHECK, before a group of steps."""
    for q in range((2 * N + 1) * B):
        work[CHECK * B + q] = work[(X + 1) * B + q]


@njit(inline="always", **FAST)
def record(work, k, h, whole, value):
    """After step k of a group (from 1) of h (s) (whole: whether the state is whole at its end): each member's
    events' values there (value(work, row, j, h, whole)) into row k of their TRACE rows.

    The loop over a block's members runs to min(B, len(work)), which is B, but not to LLVM: a loop of a known
    16 it unrolled into scalar code (six points of a chain's verlet's rate), this one it vectorizes."""
    for e in range(E):
        row = trace_row(e, k)
        for j in range(min(B, len(work))):
            work[row * B + j] = value(work, EVENT_ROWS[e], j, h, whole)


@njit(inline="always", **FAST)
def traced(work, k, j):
    """Member j's events' values (a tuple of E) in row k of their TRACE rows."""
    values = LIKE_G
    for e in range(E):
        values = tuple_setitem(values, e, work[trace_row(e, k) * B + j])
    return values


@njit(inline="always", **FAST)
def watched_group(work, context, offset, n0, steps, h, kinds, taus, levels, start):
    """After a group of `steps` steps of h (s), a save interval's steps n0 .. n0 + steps - 1 (n0 a multiple of
    CHECK_STEPS; offset: the launch's steps before the interval), each traced: whether any member's event
    crossed (`straddles`, one pass over each event's rows, in a boolean that LLVM keeps in a vector's mask), and
    where any did, each crossing located (events.located), member by member and in time: on its step n from its
    state at the step's start (start(work, j, n, h, kinds, taus)); a member stopped by one has its state NaN, and
    its later crossings are not looked at. Then each event's last value becomes the next group's first."""
    arrays, status, failure_time, j0 = context
    hits = False
    for e in range(E):
        first = trace_row(e, 0)
        for q in range(steps * B):  # q = k B + j: member j's value after step k against that after step k + 1
            hits |= straddles(work[first * B + q], work[(first + 1) * B + q], levels[e])
    if hits:
        directions = levels_and_directions(arrays[0], LIKE_G)[1]
        for j in range(B):
            for k in range(steps):
                before, after = traced(work, k, j), traced(work, k + 1, j)
                if any_crossed(before, after, levels, directions):
                    n = n0 + k
                    when = LOCATED(arrays, j0 + j, (offset + n) * h, h, start(work, j, n, h, kinds, taus),
                                   member_couplings(work, j), before, after,
                                   crossed_each(before, after, levels, directions))
                    if when == when:  # its sites' rows and the ghost between x and v NaN: this member's alone
                        stop_member(work, X + 1, 2 * N + 1, B, j, status, failure_time, j0, when)
                        break
    for e in range(E):
        first = trace_row(e, 0)
        for j in range(B):
            work[first * B + j] = work[(first + steps) * B + j]


@njit(inline="always", **FAST)
def row_value(work, row, j, h, whole):
    """A member's value in a row, as it stands."""
    return work[row * B + j]


@njit(inline="always", **FAST)
def runge_kutta_start(work, j, n, h, kinds, taus):
    """Member j's state at the start of step n of its save interval: its steps of h (s) from its last CHECK,
    replayed on a block of one."""
    y, p = member_state(work, CHECK, j, B), member_couplings(work, j)
    for _ in range(n % CHECK_STEPS):
        y = runge_kutta_advance(0.0, h, y, p)
    return y


@njit(inline="always", **FAST)
def runge_kutta_steps(work, save, h, steps_per_save, kinds, taus, context):
    """A save interval's Runge-Kutta steps of h (s) with events, in groups of CHECK_STEPS (`watched_group`)."""
    levels = levels_and_directions(context[0][0], LIKE_G)[0]
    for n0 in range(0, steps_per_save, CHECK_STEPS):
        steps = min(CHECK_STEPS, steps_per_save - n0)
        checkpoint(work)
        for k in range(1, steps + 1):
            runge_kutta_step(work, h)
            record(work, k, h, True, row_value)
        watched_group(work, context, (save - 1) * steps_per_save, n0, steps, h, kinds, taus, levels,
                      runge_kutta_start)


@njit(inline="always", **FAST)
def splitting_value(work, row, j, h, whole):
    """A member's value in a row at the end of a step of h (s) (whole: whether the state is whole there): where
    the schedule merged the step's last piece into the next step's first, the value that piece would give it
    alone (a kick's v + tau a, a drift's x + tau v; tau the last piece's)."""
    value = work[row * B + j]
    if whole:
        return value
    tau = h * FRACTIONS[len(FRACTIONS) - 1]
    if SEQUENCE[0] == KICK:
        if row >= V:
            return value + tau * site_acceleration(work, X, row - V, j, N, B)
        return value
    if row < V:
        return value + tau * work[(row - X - 1 + V) * B + j]
    return value


@njit(inline="always", **FAST)
def splitting_start(work, j, n, h, kinds, taus):
    """Member j's state at the start of step n of its save interval: the schedule's pieces (kinds, taus) from its
    last CHECK replayed on a block of one, then, where the schedule merged the last step's last piece into this
    one's first, that piece alone (of the step of h, s)."""
    per_step = pieces_per_step()
    one = one_member(member_state(work, CHECK, j, B), member_couplings(work, j))
    for p in range((n - n % CHECK_STEPS) * per_step, n * per_step):
        piece(one, kinds[p], taus[p], 1)
    if merged() and n > 0:
        piece(one, SEQUENCE[0], h * FRACTIONS[len(FRACTIONS) - 1], 1)
    return member_state(one, X + 1, 0, 1)


@njit(inline="always", **FAST)
def splitting_steps(work, save, h, steps_per_save, kinds, taus, context):
    """A save interval's splitting steps of h (s) (its schedule's pieces kinds, taus) with events, in groups of
    CHECK_STEPS (`watched_group`): a group's pieces in one loop, as the kernel without events runs them, each
    step's values recorded after its last piece (a merged schedule's last step ends with one piece more)."""
    per_step = pieces_per_step()
    count = len(kinds)
    levels = levels_and_directions(context[0][0], LIKE_G)[0]
    for n0 in range(0, steps_per_save, CHECK_STEPS):
        steps = min(CHECK_STEPS, steps_per_save - n0)
        checkpoint(work)
        for p in range(n0 * per_step, count if n0 + steps == steps_per_save else (n0 + steps) * per_step):
            piece(work, kinds[p], taus[p], B)
            last = p + 1 == count
            if last or (p + 1) % per_step == 0:  # the end of step n: row n - n0 + 1 (with %, LLVM knows it >= 0)
                n = (p - 1 if last and merged() else p) // per_step
                record(work, n % CHECK_STEPS + 1, h, last or not merged(), splitting_value)
        watched_group(work, context, (save - 1) * steps_per_save, n0, steps, h, kinds, taus, levels,
                      splitting_start)


@njit(inline="always", **FAST)
def events_adaptive_watch(work, B, context):
    """After an adaptive pair's step control, before `accept`: each event's value at the step's start (its row,
    EVENT_ROWS) against that at the trial state (rows ZX, ZV), for each member whose step was accepted; a member
    stopped by an event has its trial state NaN and takes no more steps."""
    arrays, status, failure_time, j0 = context
    levels, directions = levels_and_directions(arrays[0], LIKE_G)
    hits = 0
    for j in range(B):
        now = accepted(work, C0, B, j)
        for e in range(E):
            hits += now & straddles(work[EVENT_ROWS[e] * B + j], work[(EVENT_ROWS[e] + ZX - X) * B + j], levels[e])
    if hits:
        for j in range(B):
            before, after = watched_values(work, 0, j), watched_values(work, ZX - X, j)
            if accepted(work, C0, B, j) and any_crossed(before, after, levels, directions):
                t1, h = work[(C0 + TIME) * B + j], work[(C0 + STEP) * B + j]
                when = LOCATED(arrays, j0 + j, t1 - h, h, member_state(work, X + 1, j, B), member_couplings(work, j),
                               before, after, crossed_each(before, after, levels, directions))
                if when == when:
                    stop_member(work, ZX + 1, 2 * N + 1, B, j, status, failure_time, j0, when)
                    work[(C0 + H) * B + j] = 0.0  # no further steps


@njit(inline="always", **FAST)
def watched_values(work, offset, j):
    """Member j's events' values (a tuple of E) in their rows (EVENT_ROWS) moved by `offset` rows."""
    values = LIKE_G
    for e in range(E):
        values = tuple_setitem(values, e, work[(EVENT_ROWS[e] + offset) * B + j])
    return values


@njit(nogil=True, cache=True, **FAST)
def splitting_events_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works,
                            event_arrays, start, first_block, end_block):
    """splitting_kernel with events (ensemble.engine.events: event_arrays is a kernel call's events tuple)."""
    splitting_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                    first_block, end_block, events_begin, splitting_steps, event_arrays)


@njit(nogil=True, cache=True, **FAST)
def runge_kutta_events_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
                              works, event_arrays, start, first_block, end_block):
    """runge_kutta_kernel with events (as splitting_events_kernel)."""
    runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                      first_block, end_block, events_begin, runge_kutta_steps, event_arrays)


@njit(nogil=True, cache=True, **FAST)
def adaptive_events_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
                           works, event_arrays, start, first_block, end_block):
    """adaptive_kernel with events (as splitting_events_kernel)."""
    adaptive_frame(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                   start, first_block, end_block, no_begin, events_adaptive_watch, event_arrays)


LOCATED = locator(VALUES, {"splitting": splitting_advance, "runge_kutta": runge_kutta_advance,
                           "adaptive": adaptive_advance}[FAMILY])  # events.located for this kernel
