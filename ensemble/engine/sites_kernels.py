"""The field-of-sites kernels (ensemble.engine.sites): a splitting's, an explicit Runge-Kutta tableau's and an
embedded adaptive pair's loops over a block's members and the sites of each, each family's loops written once
(`<family>_frame`) for its kernels without and with events (`<family>_kernel`, `<family>_events_kernel`: see the
events section).

A kernel's file is this module's imports, a header that binds the names of the EXAMPLE section below to the
scene's `acceleration`, the sizes, the work rows and the method's coefficients, then the code from the CODE line
on, copied unchanged (sites.source); Numba compiles it with those names as constants. As a module, the names are
bound to an example: blocks of 4 members of 4 sites between walls, joined by unit springs, and Bogacki and
Shampine's 3(2) pair (its third-order weights as a 4-stage Runge-Kutta method) and Strang's kick-drift-kick, an
event on site 1's x, so that a test can call each kernel directly.
"""
import math

import numpy as np
from numba import njit

from ensemble.engine.blocks import (
    ATOL,
    CONTROL_ROWS,
    ERR,
    FAST,
    REJECTED_LAST,
    RTOL,
    STEP,
    TIME,
    H,
    block_done,
    cache_line_array,
    check_members,
    copy_into,
    counts_out,
    first_step,
    select,
    start_control,
    trial_steps,
)
from ensemble.engine.control import control_step
from ensemble.engine.events import (
    STOPPED,
    any_crossed,
    component,
    crossed,
    levels_and_directions,
    locator,
    values_chain,
)
from ensemble.engine.sites import (
    KICK,
    TILE_PIECES,
    TILE_ROWS,
    accept,
    drift,
    fixed_start,
    load_block,
    refresh_halos,
    saved,
    set_ghosts,
    splitting_schedule,
    stage_rows,
    stage_sums,
)
from ensemble.engine.tuples import loaded

# ---------------------------------------------------------------- EXAMPLE: what a kernel file's header binds


@njit(**FAST)
def acceleration(x_left, x, x_right, c_left, c_right):
    """The scene's acceleration (m s-2) of a site at x between neighbours at x_left and x_right."""
    return c_left * (x_left - x) + c_right * (x_right - x)


N, HALO, B, PERIODIC = 4, 0, 4, False  # sites, halo sites beyond each end of a row, members, a ring
M = N + 2 * HALO  # sites in a row
S = 4  # stages
X, V, ZX, ZV, KX, KV, C0 = stage_rows(M, S)  # first rows (see ensemble.engine.sites); C0: an adaptive pair's control
A = np.array((0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.75, 0.0, 0.0, 2 / 9, 1 / 3, 4 / 9, 0.0))  # flat S x S
WEIGHTS = (2 / 9, 1 / 3, 4 / 9, 0.0)
ERROR = (2 / 9 - 7 / 24, 1 / 3 - 1 / 4, 4 / 9 - 1 / 3, -1 / 8)  # b - b_hat: h sum_s ERROR[s] k_s, the local error
ALPHA, BETA, SAFETY, MIN_FACTOR, MAX_FACTOR = 0.7 / 3 - 0.75 * 0.04, 0.04, 0.9, 0.2, 10.0
SEQUENCE, FRACTIONS = (0, 1, 0), (0.5, 1.0, 0.5)  # piece numbers (KICK or drift), fractions of the step
TILED = False
FAMILY = "runge_kutta"  # the method's family: which step its events are located on (LOCATED)
E, EVENT_ROWS, FIRST_EVENT = 1, (X + 1,), C0 + CONTROL_ROWS  # events: each one's work row, the events' first row
VALUES = values_chain((component(0),))  # each event's value on a member's state (x; v): here site 1's x

# ---------------------------------------------------------------- CODE: copied into every kernel's file


@njit(inline="always", **FAST)
def site_acceleration(work, x, i, j, n, B):
    """Acceleration (m s-2) of site i + 1 of member j, from the positions at row x (with ghosts)."""
    CL, CR = 2 * n + 2, 3 * n + 2
    return acceleration(work[(x + i) * B + j], work[(x + 1 + i) * B + j], work[(x + 2 + i) * B + j],
                        work[(CL + i) * B + j], work[(CR + i) * B + j])


@njit(inline="always", **FAST)
def slopes(work, zx, zv, kx, kv, n, B):
    """A stage's slopes: velocities from row zv into row kx, accelerations from row zx into row kv.

    One loop over the n x B values (site i, member j at i B + j): a stage's rows kx, kv are known only at run
    time, and over a block's B members alone LLVM does not check them against the rows read, so it did not
    vectorize (a chain's dopri5 spent a third of its time here, scalar)."""
    for q in range(n * B):
        work[kx * B + q] = work[zv * B + q]
        work[kv * B + q] = site_acceleration(work, zx, 0, q, n, B)  # q = i B + j: site i + 1, member j


@njit(inline="always", **FAST)
def stage(work, s, a, h, step_row, B):
    """Runge-Kutta stage s of a block of B members: its state Z = Y + sum_r h a[s, r] K_r into rows ZX, ZV, then
    its slopes into KX_s, KV_s. The step is h, or each member's own from row step_row when step_row >= 0
    (adaptive kernels); a is the flat stages x stages tableau, zero from column s."""
    for i in range(N):
        for j in range(B):
            hj = work[step_row * B + j] if step_row >= 0 else h
            zx = work[(X + 1 + i) * B + j]
            zv = work[(V + i) * B + j]
            for r in range(S):
                ha = hj * a[s * S + r]
                zx += ha * work[(KX + r * N + i) * B + j]
                zv += ha * work[(KV + r * N + i) * B + j]
            work[(ZX + 1 + i) * B + j] = zx
            work[(ZV + i) * B + j] = zv
    set_ghosts(work, ZX, N, B, PERIODIC)
    slopes(work, ZX, ZV, KX + s * N, KV + s * N, N, B)


@njit(inline="always", **FAST)
def kick(work, tau, lo, hi, n, B):
    """Kick sites lo + 1 .. hi: v += tau (s) times their acceleration."""
    w = work[lo * B:]  # rows from lo on, indexed from 0
    for q in range((hi - lo) * B):  # q = i B + j: site lo + i + 1, member j
        w[(n + 2) * B + q] += tau * site_acceleration(w, 0, 0, q, n, B)


@njit(inline="always", **FAST)
def piece(work, kind, tau, B):
    """One piece of a splitting (KICK or drift, of tau s) over every site of a block of B members."""
    if kind == KICK:
        kick(work, tau, 0, N, N, B)
    else:
        drift(work, tau, 0, N, N, B)
        set_ghosts(work, X, N, B, PERIODIC)


@njit(inline="always", **FAST)
def pieces(work, kinds, taus, first, end):
    """Pieces first .. end - 1 of a splitting's schedule (kinds, taus: splitting_schedule) over a block's sites,
    one piece at a time."""
    for p in range(first, end):
        piece(work, kinds[p], taus[p], B)


@njit(inline="always", **FAST)
def merged():
    """Whether a splitting's step ends with the piece the next begins with (verlet: a half kick): a save
    interval's schedule merges the two (splitting_schedule)."""
    return len(SEQUENCE) > 1 and SEQUENCE[0] == SEQUENCE[len(SEQUENCE) - 1]


# A long chain's rows outgrow the L1 cache (tiles), so its splitting kernel runs TILE_PIECES pieces (kicks and
# drifts) at once over tiles of TILE_ROWS sites, each piece one site behind the piece before it where kick and drift
# alternate (a wavefront): every site still sees its neighbours as the one-piece-at-a-time order has them, so
# results are bit for bit the same. A ring's ends need each other's last piece, so a long ring's rows hold HALO more
# sites on each side (ring_halo), copies of the sites at its other end made before each run of pieces: a wrong
# value at a row's end travels one site a kick, so it never reaches the ring's own sites, which take the same bits
# as one piece at a time. A short ring copies its ghost sites after each drift. Kick and drift make one loop over
# their sites' values (site i, member j at i B + j), indexed from 0 in a view of the work array: from a variable
# start, Numba's negative-index wraparound stays in the loop and LLVM does not vectorize it. As two loops (sites,
# then a block's B members, unrolled), LLVM on AVX-512 vectorized the loop over sites, with gathers: a tenth of the
# speed. With events (E > 0) the kernel is not tiled, and watches after each step's pieces of the same schedule
# (`merged` pieces included), so its samples are those of the kernel without events.
@njit(inline="always", **FAST)
def splitting_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                    first_block, end_block, begin, remember, watch, locate, events):
    """The splitting kernels' loops (`splitting_kernel`); begin, remember, watch, locate: the events'
    (events_begin, events_remember, splitting_watch, splitting_locate) or no_begin, no_remember, no_watch,
    no_locate;
    events their arrays or (). A step in which an event crossed leaves the loop of steps, to locate it: a call
    in that loop, even one never made, cost a chain's verlet a third of its rate."""
    kinds, taus, lags = splitting_schedule(SEQUENCE, FRACTIONS, h, steps_per_save, TILE_PIECES)
    count = len(kinds)
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        context = (events, status, failure_time, block * B)
        if not fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start,
                           N, HALO, B, PERIODIC):
            continue
        if start == 0:
            begin(work, B, context)
        for save in range(max(start, 1), start + samples.shape[1]):
            if TILED:
                for c0 in range(0, count, TILE_PIECES):
                    c1 = min(c0 + TILE_PIECES, count)
                    refresh_halos(work, N, HALO, B)
                    for t0 in range(0, M + lags[c1 - 1], TILE_ROWS):
                        for p in range(c0, c1):
                            lo = max(t0 - lags[p], 0)
                            hi = min(t0 + TILE_ROWS - lags[p], M)
                            if kinds[p] == KICK:
                                kick(work, taus[p], lo, hi, M, B)
                            else:
                                drift(work, taus[p], lo, hi, M, B)
            elif E > 0:
                per_step = len(SEQUENCE) - 1 if merged() else len(SEQUENCE)  # pieces from one step's to the next's
                n = 0
                while n < steps_per_save:
                    hits = 0
                    while hits == 0 and n < steps_per_save:  # steps until an event crosses: no call in this loop
                        first = n * per_step
                        end = count if n == steps_per_save - 1 else first + per_step
                        remember(work, B, n)
                        pieces(work, kinds, taus, first, end)
                        hits = watch(work, B, h, context, end == count)
                        n += 1
                    if hits:
                        locate(work, context, n - 1, ((save - 1) * steps_per_save + n - 1) * h, h, kinds, taus)
            else:
                pieces(work, kinds, taus, 0, count)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress,
                     save * steps_per_save * h, -1, N, HALO, B):
                break
        copy_into(works[block], work)


@njit(nogil=True, cache=True, **FAST)
def splitting_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                     first_block, end_block):
    """state0 (blocks, 2n, B), rate (blocks, 2n, B), limit (M,) -> samples (members, count, 2n),
    status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x B."""
    splitting_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                    first_block, end_block, no_begin, no_remember, no_watch, no_locate, ())


@njit(nogil=True, cache=True, **FAST)
def splitting_events_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works,
                            event_arrays, start, first_block, end_block):
    """splitting_kernel with events (ensemble.engine.events: event_arrays is a kernel call's events tuple)."""
    splitting_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                    first_block, end_block, events_begin, events_remember, splitting_watch, splitting_locate,
                    event_arrays)


@njit(inline="always", **FAST)
def runge_kutta_step(work, h):
    """A block's Runge-Kutta step of h (s): the tableau A (flat S x S), WEIGHTS."""
    for s in range(S):
        stage(work, s, A, h, -1, B)
    for i in range(N):
        for j in range(B):
            dx, dv = stage_sums(work, WEIGHTS, S, KX, KV, i, j, N, B)
            work[(X + 1 + i) * B + j] += h * dx
            work[(V + i) * B + j] += h * dv


@njit(inline="always", **FAST)
def runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works,
                      start, first_block, end_block, begin, remember, watch, locate, events):
    """The Runge-Kutta kernels' loops, for the tableau A (flat S x S), WEIGHTS; the rest as splitting_frame."""
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        context = (events, status, failure_time, block * B)
        if not fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start,
                           N, 0, B, PERIODIC):
            continue
        if start == 0:
            begin(work, B, context)
        for save in range(max(start, 1), start + samples.shape[1]):
            if E > 0:
                n = 0
                while n < steps_per_save:
                    hits = 0
                    while hits == 0 and n < steps_per_save:  # as splitting_frame's
                        remember(work, B, n)
                        runge_kutta_step(work, h)
                        hits = watch(work, B, h, context, True)
                        n += 1
                    if hits:
                        locate(work, context, n - 1, ((save - 1) * steps_per_save + n - 1) * h, h, (), ())
            else:
                for _ in range(steps_per_save):
                    runge_kutta_step(work, h)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress,
                     save * steps_per_save * h, -1, N, 0, B):
                break
        copy_into(works[block], work)


@njit(nogil=True, cache=True, **FAST)
def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works,
                       start, first_block, end_block):
    """As splitting_kernel, for the tableau A (flat S x S), WEIGHTS."""
    runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                      first_block, end_block, no_begin, no_remember, no_watch, no_locate, ())


@njit(nogil=True, cache=True, **FAST)
def runge_kutta_events_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
                              works, event_arrays, start, first_block, end_block):
    """runge_kutta_kernel with events (as splitting_events_kernel)."""
    runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                      first_block, end_block, events_begin, events_remember, runge_kutta_watch, runge_kutta_locate,
                      event_arrays)


@njit(inline="always", **FAST)
def first_steps(work, control, j0, save_dt):
    """Each member's control rows at its start: its first trial step (s) is control[0] where that is > 0, else
    guessed from its state and slopes (blocks.first_step)."""
    for j in range(B):
        rtol, atol = control[1, j0 + j], control[2, j0 + j]
        h = control[0, j0 + j]
        if h <= 0.0:
            size = 0.0
            slope = 0.0
            for i in range(N):
                x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                size = max(size, abs(x) / (atol + rtol * abs(x)), abs(v) / (atol + rtol * abs(v)))
                slope = max(slope, abs(v) / (atol + rtol * abs(x)),
                            abs(work[(KV + i) * B + j]) / (atol + rtol * abs(v)))
            h = first_step(size, slope, save_dt)
        start_control(work, C0, B, j, rtol, atol, h)


@njit(inline="always", **FAST)
def error_norms(work):
    """Each member's trial step's error norm into its ERR row: the root mean square over its 2N values of
    h sum_s ERROR[s] k_s, each scaled by atol + rtol max(|y|, |new y|)."""
    for i in range(N):
        for j in range(B):
            ex, ev = stage_sums(work, ERROR, S, KX, KV, i, j, N, B)
            h = work[(C0 + STEP) * B + j]
            rtol, atol = work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j]
            x, z = work[(X + 1 + i) * B + j], work[(ZX + 1 + i) * B + j]
            qx = h * ex / (atol + rtol * max(abs(x), abs(z)))
            v, z = work[(V + i) * B + j], work[(ZV + i) * B + j]
            qv = h * ev / (atol + rtol * max(abs(v), abs(z)))
            work[(C0 + ERR) * B + j] += qx * qx + qv * qv
    for j in range(B):
        work[(C0 + ERR) * B + j] = math.sqrt(work[(C0 + ERR) * B + j] / (2 * N))


# As for a member of D values (ensemble.engine.frames.adaptive), every member of a block takes its own trial step at
# once, clipped to land on the next saved time.
@njit(inline="always", **FAST)
def adaptive_frame(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                   start, first_block, end_block, begin, watch, events):
    """The adaptive kernels' loops (`adaptive_kernel`); begin, watch: the events' (events_begin,
    events_adaptive_watch) or no_begin twice, events their arrays or ()."""
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        j0 = block * B
        context = (events, status, failure_time, j0)
        copy_into(work, works[block])
        if start == 0:
            load_block(work, state0, rate, block, samples, N, 0, B, PERIODIC)
            slopes(work, X, V, KX, KV, N, B)
            first_steps(work, control, j0, save_dt)
            # a non-finite start
            check_members(work, X + 1, 2 * N + 1, B, j0, limit, status, failure_time, 0.0, C0 + H)
            begin(work, B, context)
        elif block_done(samples, status, progress, block, B):
            continue
        for save in range(max(start, 1), start + samples.shape[1]):
            target = save * save_dt
            while trial_steps(work, C0, B, target):
                for s in range(1, S):  # FSAL: stage 0 is the last step's final stage
                    stage(work, s, A, 0.0, C0 + STEP, B)
                error_norms(work)  # FSAL: the last stage state ZX, ZV is the new state
                control_step(work, C0, B, target, j0, status, failure_time, S - 1, ALPHA, BETA, SAFETY, MIN_FACTOR,
                             MAX_FACTOR)
                watch(work, B, context)
                accept(work, X, V, ZX, ZV, KX, KV, C0, S, N, B)
                set_ghosts(work, X, N, B, PERIODIC)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress, target, C0 + H, N, 0,
                     B):
                break
        counts_out(work, C0, B, counts, j0)
        copy_into(works[block], work)


@njit(nogil=True, cache=True, **FAST)
def adaptive_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                    start, first_block, end_block):
    """state0, rate (blocks, 2n, B); control (3, M): first step (s; <= 0: estimate it), rtol, atol;
    limit (M,) -> samples (members, count, 2n), counts (3, M): accepted, rejected, right-hand-side evaluations;
    status (M,) and failure_time (M,; s, set only where a member fails)."""
    adaptive_frame(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                   start, first_block, end_block, no_begin, no_begin, ())


@njit(nogil=True, cache=True, **FAST)
def adaptive_events_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
                           works, event_arrays, start, first_block, end_block):
    """adaptive_kernel with events (as splitting_events_kernel)."""
    adaptive_frame(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
                   start, first_block, end_block, events_begin, events_adaptive_watch, event_arrays)


# ---------------------------------------------------------------- events
# A member's events watch sites' values (ensemble.engine.events): EVENT_ROWS holds each one's work row (X + 1 + k
# for site k + 1's x, V + k for its v). The rows from FIRST_EVENT: G (E: the values at the step's end), BEFORE (E:
# at its start; an adaptive kernel's values after its trial step) and, for fixed steps, CHECK (2N + 1: the rows
# X + 1 .. V + N - 1 as they were at a save interval's step n, n a multiple of CHECK_STEPS). A crossing is located
# on the method's own step of one member (`advance`: the kernel's arithmetic on a block of one member) from its
# state at the step's start, as a member family's is: an adaptive pair's is still in rows X, V; a fixed step's is
# replayed on a block of one from CHECK (at most CHECK_STEPS - 1 steps), so that a step keeps no copy of the
# block's state (a copy at every step cost a chain's verlet a third of its rate). Its states go to the event
# arrays as (x; v), 2N values.
G, BEFORE, CHECK = FIRST_EVENT, FIRST_EVENT + E, FIRST_EVENT + 2 * E
CHECK_STEPS = 32
LIKE_G = (0.0,) * E


@njit(inline="always", **FAST)
def no_begin(work, B, context):
    """A kernel without events: nothing at its start (nor after an adaptive step's control)."""


@njit(inline="always", **FAST)
def no_remember(work, B, n):
    """A kernel without events: nothing kept before a step."""


@njit(inline="always", **FAST)
def no_watch(work, B, h, context, whole):
    """A kernel without events: no event crossed in a fixed step."""
    return 0


@njit(inline="always", **FAST)
def no_locate(work, context, n, t, h, kinds, taus):
    """A kernel without events: nothing to locate."""


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
def stopped_at(work, first, j, status, failure_time, j0, when):
    """Member j stops at an event at `when` (s): status STOPPED, failure_time (the launch counts its steps up to it)
    and its sites' rows from `first` (x at first + i, v at first + N + 1 + i) NaN."""
    status[j0 + j] = STOPPED
    failure_time[j0 + j] = when
    for i in range(N):
        work[(first + i) * B + j] = np.nan
        work[(first + N + 1 + i) * B + j] = np.nan


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
    the step's end (value(work, row, j, h, whole)) into rows G, those at its start into rows BEFORE; how many
    crossed. context: (event arrays, status, failure_time, j0)."""
    levels, directions = levels_and_directions(context[0][0], LIKE_G)
    hits = 0
    for e in range(E):  # a loop over a block's members inside: LLVM vectorizes it
        row, level, direction = EVENT_ROWS[e], levels[e], directions[e]
        for j in range(B):
            before, after = work[(G + e) * B + j], value(work, row, j, h, whole)
            work[(BEFORE + e) * B + j] = before
            work[(G + e) * B + j] = after
            hits += crossed(before, after, level, direction)
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
                           before, after)
            if when == when:
                stopped_at(work, X + 1, j, status, failure_time, j0, when)


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


@njit(**FAST)
def runge_kutta_located(work, context, n, t, h):
    located_members(work, context, n, t, h, (), (), runge_kutta_start)


@njit(inline="always", **FAST)
def runge_kutta_watch(work, B, h, context, whole):
    """After a Runge-Kutta step of h (s): how many of the block's members' events crossed (`crossings`)."""
    return crossings(work, B, h, whole, context, row_value)


@njit(inline="always", **FAST)
def runge_kutta_locate(work, context, n, t, h, kinds, taus):
    """After a Runge-Kutta step n of a save interval, of h (s) from t (s), in which an event crossed: located."""
    runge_kutta_located(work, context, n, t, h)


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


@njit(**FAST)
def splitting_located(work, context, n, t, h, kinds, taus):
    located_members(work, context, n, t, h, kinds, taus, splitting_start)


@njit(inline="always", **FAST)
def splitting_watch(work, B, h, context, whole):
    """After a splitting's step of h (s) (whole: whether its last piece was its own, not merged into the next
    step's first): how many of the block's members' events crossed (`crossings`)."""
    return crossings(work, B, h, whole, context, splitting_value)


@njit(inline="always", **FAST)
def splitting_locate(work, context, n, t, h, kinds, taus):
    """After a splitting's step n of a save interval (its pieces of the schedule kinds, taus), of h (s) from t
    (s), in which an event crossed: located."""
    splitting_located(work, context, n, t, h, kinds, taus)


@njit(inline="always", **FAST)
def events_adaptive_watch(work, B, context):
    """After an adaptive pair's step control, before `accept`: as fixed_watch, the trial states (rows ZX, ZV)
    against the states (rows X, V) for each member whose step was accepted; a member stopped by an event has its
    trial state NaN and takes no more steps."""
    arrays, status, failure_time, j0 = context
    levels, directions = levels_and_directions(arrays[0], LIKE_G)
    hits = 0
    for j in range(B):
        accepted = (work[(C0 + REJECTED_LAST) * B + j] == 0.0) & (work[(C0 + ERR) * B + j] >= 0.0)
        for e in range(E):
            before, after = work[(G + e) * B + j], work[(EVENT_ROWS[e] + ZX - X) * B + j]
            work[(BEFORE + e) * B + j] = select(accepted, after, before)
            hits += accepted & crossed(before, after, levels[e], directions[e])
    if hits:
        for j in range(B):
            before, after = loaded(work, G, B, j, LIKE_G), loaded(work, BEFORE, B, j, LIKE_G)
            if any_crossed(before, after, levels, directions):
                t1, h = work[(C0 + TIME) * B + j], work[(C0 + STEP) * B + j]
                when = LOCATED(arrays, j0 + j, t1 - h, h, member_state(work, X + 1, j, B), member_couplings(work, j),
                               before, after)
                if when == when:
                    stopped_at(work, ZX + 1, j, status, failure_time, j0, when)
                    work[(C0 + H) * B + j] = 0.0  # no further steps
    for e in range(E):
        for j in range(B):
            work[(G + e) * B + j] = work[(BEFORE + e) * B + j]


LOCATED = locator(VALUES, {"splitting": splitting_advance, "runge_kutta": runge_kutta_advance,
                           "adaptive": adaptive_advance}[FAMILY])  # events.located for this kernel
