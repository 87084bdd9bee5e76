"""The field-of-sites kernels (ensemble.engine.sites): a splitting's, an explicit Runge-Kutta tableau's and an
embedded adaptive pair's loops over a block's members and the sites of each, each family's loops written once
(`<family>_frame`) for its kernel without events (`<family>_kernel`, here) and with them
(ensemble.engine.sites_events).

A kernel's file is this module's imports, a header that binds the names of the EXAMPLE section below to the
scene's `acceleration`, the sizes, the work rows and the method's coefficients, then the code from the CODE line
on, copied unchanged (sites.source); Numba compiles it with those names as constants. As a module, the names are
bound to an example: blocks of 4 members of 4 sites between walls, joined by unit springs, and Bogacki and
Shampine's 3(2) pair (its third-order weights as a 4-stage Runge-Kutta method) and Strang's kick-drift-kick,
so that a test can call each kernel directly.
"""
import math

import numpy as np
from numba import njit

from ensemble.engine.blocks import (
    ATOL,
    ERR,
    FAST,
    RTOL,
    STEP,
    H,
    block_done,
    cache_line_array,
    check_members,
    copy_into,
    counts_out,
    first_step,
    start_control,
    trial_steps,
)
from ensemble.engine.control import control_step
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
E = 1  # events (ensemble.engine.sites_events's example watches one)

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


@njit(inline="always", **FAST)
def pieces_per_step():
    """Pieces of a save interval's schedule from one step's first to the next's (one fewer than SEQUENCE's where
    the schedule merges a step's last piece into the next step's first)."""
    return len(SEQUENCE) - 1 if merged() else len(SEQUENCE)


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
# speed. With events the kernel is not tiled, and watches after each step's pieces of the same schedule (`merged`
# pieces included), so its samples are those of the kernel without events.
@njit(inline="always", **FAST)
def splitting_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                    first_block, end_block, begin, steps, events):
    """The splitting kernels' loops (`splitting_kernel`); begin, steps: the events' (events_begin at the start,
    splitting_steps for a save interval's steps, untiled) or no_begin, splitting_steps_alone; events their
    arrays or ()."""
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
            else:
                steps(work, save, h, steps_per_save, kinds, taus, context)
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
                    first_block, end_block, no_begin, splitting_steps_alone, ())


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
                      start, first_block, end_block, begin, steps, events):
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
            steps(work, save, h, steps_per_save, (), (), context)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress,
                     save * steps_per_save * h, -1, N, 0, B):
                break
        copy_into(works[block], work)


@njit(nogil=True, cache=True, **FAST)
def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works,
                       start, first_block, end_block):
    """As splitting_kernel, for the tableau A (flat S x S), WEIGHTS."""
    runge_kutta_frame(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
                      first_block, end_block, no_begin, runge_kutta_steps_alone, ())


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


# ---------------------------------------------------------------- a kernel without events: nothing


@njit(inline="always", **FAST)
def no_begin(work, B, context):
    """A kernel without events: nothing at its start (nor after an adaptive step's control)."""


@njit(inline="always", **FAST)
def splitting_steps_alone(work, save, h, steps_per_save, kinds, taus, context):
    """A save interval's splitting steps without events (untiled): its schedule's pieces (kinds, taus), one at a
    time."""
    pieces(work, kinds, taus, 0, len(kinds))


@njit(inline="always", **FAST)
def runge_kutta_steps_alone(work, save, h, steps_per_save, kinds, taus, context):
    """A save interval's steps_per_save Runge-Kutta steps of h (s), without events."""
    for _ in range(steps_per_save):
        runge_kutta_step(work, h)
