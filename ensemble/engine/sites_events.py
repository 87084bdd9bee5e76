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
from ensemble.engine.sites import KICK, set_ghosts, stage_sums
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
    runge_kutta_frame,
    site_acceleration,
    slopes,
    splitting_frame,
    stage,
)
from ensemble.engine.tuples import loaded

# ---------------------------------------------------------------- EXAMPLE: what a kernel file's header binds

FAMILY = "runge_kutta"  # the method's family: which step its events are located on (LOCATED)
EVENT_ROWS, FIRST_EVENT = (X + 1,), C0 + CONTROL_ROWS  # each event's work row, the events' first row
VALUES = values_chain((component(0),))  # each event's value on a member's state (x; v): here site 1's x

# ---------------------------------------------------------------- CODE: copied into a kernel's file with events
# EVENT_ROWS holds each event's work row. A fixed step's kernel has rows from FIRST_EVENT: G (E: the values at the
# step's end), BEFORE (E: at its start) and CHECK (2N + 1: the rows X + 1 .. V + N - 1 as they were at a save
# interval's step n, n a multiple of CHECK_STEPS); an adaptive kernel needs none, its trial state being in rows of
# its own (ZX, ZV) until `accept`. A crossing is located on the method's own step of one member (`advance`: the
# kernel's arithmetic on a block of one member) from its state at the step's start, as a member family's is: an
# adaptive pair's is still in rows X, V; a fixed step's is replayed on a block of one from CHECK (at most
# CHECK_STEPS - 1 steps), so that a step keeps no copy of the block's state (a copy at every step cost a chain's
# verlet a third of its rate). Its states go to the event arrays as (x; v), 2N values.
G, BEFORE, CHECK = FIRST_EVENT, FIRST_EVENT + E, FIRST_EVENT + 2 * E
CHECK_STEPS = 32
LIKE_G = (0.0,) * E


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
    """The block's events' values at t = 0 into rows G."""
    for e in range(E):
        for j in range(B):
            work[(G + e) * B + j] = work[EVENT_ROWS[e] * B + j]


@njit(inline="always", **FAST)
def events_remember(work, B, n):
    """Before step n of a save interval: every CHECK_STEPS steps, the block's state (rows X + 1 .. V + N - 1) into
    rows CHECK."""
    if n % CHECK_STEPS == 0:
        for q in range((2 * N + 1) * B):
            work[CHECK * B + q] = work[(X + 1) * B + q]


@njit(inline="always", **FAST)
def crossings(work, B, h, whole, context, value):
    """After a fixed step of h (s) (whole: whether the state is whole at its end): each member's events' values at
    the step's end (value(work, row, j, h, whole)) into rows G, those at its start into rows BEFORE; whether any
    may have crossed (`straddles`: located_members finds which did). context: (event arrays, status,
    failure_time, j0).

    The loop over a block's members runs to min(B, len(work)), which is B, but not to LLVM: a loop of a known
    16 it unrolled into scalar code (six points of a chain's verlet's rate), this one it vectorizes; `hits`
    is a boolean, which it keeps in a vector's mask."""
    levels, _ = levels_and_directions(context[0][0], LIKE_G)
    hits = False
    members = min(B, len(work))
    for e in range(E):
        row, level = EVENT_ROWS[e], levels[e]
        for j in range(members):
            before, after = work[(G + e) * B + j], value(work, row, j, h, whole)
            work[(BEFORE + e) * B + j] = before
            work[(G + e) * B + j] = after
            hits |= straddles(before, after, level)
    return hits


@njit(inline="always", **FAST)
def located_members(work, context, n, t, h, kinds, taus, start):
    """After a save interval's step n of h (s) from t (s) in which an event crossed: each such member's events
    located on its step from its state at the step's start (start(work, j, n, h, kinds, taus); LOCATED:
    ensemble.engine.events.located); a member stopped by one has its state NaN."""
    arrays, status, failure_time, j0 = context
    levels, directions = levels_and_directions(arrays[0], LIKE_G)
    for j in range(B):
        before, after = loaded(work, BEFORE, B, j, LIKE_G), loaded(work, G, B, j, LIKE_G)
        if any_crossed(before, after, levels, directions):
            when = LOCATED(arrays, j0 + j, t, h, start(work, j, n, h, kinds, taus), member_couplings(work, j),
                           before, after, crossed_each(before, after, levels, directions))
            if when == when:  # its sites' rows and the ghost between x and v NaN: this member's alone
                stop_member(work, X + 1, 2 * N + 1, B, j, status, failure_time, j0, when)


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
def runge_kutta_watch(work, B, h, context, whole):
    """After a Runge-Kutta step of h (s): whether any of the block's members' events crossed (`crossings`)."""
    return crossings(work, B, h, whole, context, row_value)


@njit(inline="always", **FAST)
def runge_kutta_locate(work, context, n, t, h, kinds, taus):
    """After a Runge-Kutta step n of a save interval, of h (s) from t (s), in which an event crossed: located."""
    located_members(work, context, n, t, h, kinds, taus, runge_kutta_start)


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
    per_step = len(SEQUENCE) - 1 if merged() else len(SEQUENCE)
    one = one_member(member_state(work, CHECK, j, B), member_couplings(work, j))
    for p in range((n - n % CHECK_STEPS) * per_step, n * per_step):
        piece(one, kinds[p], taus[p], 1)
    if merged() and n > 0:
        piece(one, SEQUENCE[0], h * FRACTIONS[len(FRACTIONS) - 1], 1)
    return member_state(one, X + 1, 0, 1)


@njit(inline="always", **FAST)
def splitting_watch(work, B, h, context, whole):
    """After a splitting's step of h (s) (whole: whether its last piece was its own, not merged into the next
    step's first): whether any of the block's members' events crossed (`crossings`)."""
    return crossings(work, B, h, whole, context, splitting_value)


@njit(inline="always", **FAST)
def splitting_locate(work, context, n, t, h, kinds, taus):
    """After a splitting's step n of a save interval (its pieces of the schedule kinds, taus), of h (s) from t
    (s), in which an event crossed: located."""
    located_members(work, context, n, t, h, kinds, taus, splitting_start)


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
            before, after = event_values(work, 0, j), event_values(work, ZX - X, j)
            if accepted(work, C0, B, j) and any_crossed(before, after, levels, directions):
                t1, h = work[(C0 + TIME) * B + j], work[(C0 + STEP) * B + j]
                when = LOCATED(arrays, j0 + j, t1 - h, h, member_state(work, X + 1, j, B), member_couplings(work, j),
                               before, after, crossed_each(before, after, levels, directions))
                if when == when:
                    stop_member(work, ZX + 1, 2 * N + 1, B, j, status, failure_time, j0, when)
                    work[(C0 + H) * B + j] = 0.0  # no further steps


@njit(inline="always", **FAST)
def event_values(work, offset, j):
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
                    first_block, end_block, events_begin, events_remember, splitting_watch, splitting_locate,
                    event_arrays)


@njit(nogil=True, cache=True, **FAST)
def runge_kutta_events_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
                              works, event_arrays, start, first_block, end_block):
    """runge_kutta_kernel with events (as splitting_events_kernel)."""
    runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                      first_block, end_block, events_begin, events_remember, runge_kutta_watch, runge_kutta_locate,
                      event_arrays)


@njit(nogil=True, cache=True, **FAST)
def adaptive_events_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
                           works, event_arrays, start, first_block, end_block):
    """adaptive_kernel with events (as splitting_events_kernel)."""
    adaptive_frame(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                   start, first_block, end_block, no_begin, events_adaptive_watch, event_arrays)


LOCATED = locator(VALUES, {"splitting": splitting_advance, "runge_kutta": runge_kutta_advance,
                           "adaptive": adaptive_advance}[FAMILY])  # events.located for this kernel
