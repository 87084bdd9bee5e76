"""The method families' CUDA kernels for a member of D state values and P parameters (ensemble.engine.gpu): a
GPU thread per member, its state a tuple in registers, stepped by the CPU kernels' own code for one member
(runge_kutta.step, adaptive.trial_step and .error_norm, control.controlled, the splittings' chains: gpu_device
compiles them as device functions). The arrays are in (rows, members) order, so that neighbouring threads touch
neighbouring memory: state0 and rate (D and P rows) and the samples (count, D, members) in REAL, works (rows,
members) in float64, where a kernel call leaves each member for the next.

A kernel's file is the GPU kernels' header (gpu.HEADER: REAL, D, P, NAN, TINY, ZERO, the scene's functions, the
step control), this module's imports, the names of the EXAMPLE section below bound to the method's, then the code
from the CODE line on, unchanged, and the footer's choices (gpu.member_kernel). As a module, the names are bound to
an example: a harmonic oscillator (x, v; omega) in float64, Bogacki and Shampine's 3(2) pair (its third-order
weights as a 4-stage Runge-Kutta method), and Strang's kick-drift-kick.
"""
import math

from numba import cuda, float64

from ensemble.engine import adaptive, runge_kutta, splitting
from ensemble.engine.blocks import FIRST_LOG2_ERR_PREVIOUS
from ensemble.engine.gpu import BLEW_UP, OK, STOPPED, UNDERFLOW
from ensemble.engine.gpu_device import (
    device_events,
    device_function,
    device_helpers,
    device_inlined,
    device_tuples,
    device_unrolled,
)

# ---------------------------------------------------------------- EXAMPLE: what a kernel file's header binds


@cuda.jit(device=True)
def rhs(t, x, v, omega):
    """The scene's slopes (x', v') at time t (s)."""
    return v, -omega * omega * x


@cuda.jit(device=True)
def kick(tau, x, v, omega):
    return x, v - tau * omega * omega * x


@cuda.jit(device=True)
def drift(tau, x, v, omega):
    return x + tau * v, v


counted, first_step = device_helpers()
REAL = float64
D, P = 2, 1  # state values, parameters
NAN, TINY, ZERO = REAL(math.nan), REAL(2.2250738585072014e-308), REAL(0.0)
STAGES = tuple(tuple(REAL(a) for a in row) for row in (  # Butcher rows (c_s, a_s0, .., a_s,S-1)
    (0.0, 0.0, 0.0, 0.0, 0.0), (0.5, 0.5, 0.0, 0.0, 0.0), (0.75, 0.0, 0.75, 0.0, 0.0),
    (1.0, 2 / 9, 1 / 3, 4 / 9, 0.0)))
WEIGHTS = tuple(REAL(b) for b in (2 / 9, 1 / 3, 4 / 9, 0.0))
ERROR = tuple(REAL(e) for e in (2 / 9 - 7 / 24, 1 / 3 - 1 / 4, 4 / 9 - 1 / 3, -1 / 8))
S = len(STAGES)
STAGE_LOOP = device_unrolled(S)  # the stages, written out (tuples.unrolled)
CONTROLLER = (0.7 / 3 - 0.75 * 0.04, 0.04, 0.9, 0.2, 10.0)  # alpha, beta, safety, min_factor, max_factor
split_step = splitting.sequence_step(((kick, REAL(0.5)), (drift, REAL(1.0)), (kick, REAL(0.5))), device_inlined)
split_factors = splitting.sequence_factors(((None, REAL(0.5)), (None, REAL(1.0)), (None, REAL(0.5))),
                                           device_inlined)
E = 0  # events (an event kernel's header binds E, VALUES and SIGNS: gpu_device.device_event_values, _signs)


@cuda.jit(device=True, inline="always")
def VALUES(t, y, p):
    """Each event's value (float64) at time t (s) of a member's state y and parameters p (tuples)."""
    return ()


@cuda.jit(device=True, inline="always")
def SIGNS(t, y, p, levels):
    """Each event's sign against its level (ensemble.engine.events.signs_chain), as VALUES."""
    return ()

# ---------------------------------------------------------------- CODE: copied into every kernel's file

loaded, stored, converted, repeated, tuple_setitem = device_tuples()
rk_step = device_function(runge_kutta.step)
trial_step, error_norm = device_function(adaptive.trial_step), device_function(adaptive.error_norm)
LIKE_Y, LIKE_P, WIDE_Y = (ZERO,) * D, (ZERO,) * P, (0.0,) * D  # a state and parameters in REAL, a state in float64
WIDE_CONTROL = (0.0,) * 7  # an adaptive member's time, step, log2 of its last error, rejected last, counts
LIKE_G = (0.0,) * E  # the events' signs
crossed, located = device_events()


@cuda.jit(device=True, inline="always")
def levels_of(spec):
    """The events' levels (spec's first column) as a tuple of E."""
    levels = repeated(0.0, LIKE_G)
    for e in range(E):
        levels = tuple_setitem(levels, e, spec[e, 0])
    return levels


@cuda.jit(device=True, inline="always")
def flushed(y):
    """y, its subnormal values zeros of their sign, as the CPU's check_members makes them (at the start and each
    save), so that both give the same bits."""
    for c in range(D):
        y = tuple_setitem(y, c, y[c] if abs(y[c]) >= TINY else y[c] * ZERO)
    return y


@cuda.jit(device=True, inline="always")
def failed(y, limit):
    """Whether a value of y is not finite or beyond `limit` (the CPU's check_members)."""
    bad = False
    for c in range(D):
        bad = bad or not abs(y[c]) <= limit or math.isinf(y[c])
    return bad


@cuda.jit(device=True, inline="always")
def first_state(state0, m):
    return flushed(converted(loaded(state0, 0, state0.shape[1], m, LIKE_Y), LIKE_Y))


@cuda.jit(device=True, inline="always")
def started(y, limit, samples, status, failure_time, m):
    """A member's first state y: failed at t = 0 if a value is not finite or beyond its limit (then NaN); sample 0."""
    if failed(y, limit[m]):
        status[m], failure_time[m] = BLEW_UP, 0.0
        y = repeated(NAN, LIKE_Y)
    stored(samples, 0, samples.shape[2], m, y)
    return y


@cuda.jit(device=True, inline="always")
def saved(y, limit, samples, status, failure_time, i, m, t):
    """The end of save interval i at time t (s): a running member that has failed stops (status BLEW_UP, its
    state NaN); sample i stored. The state, flushed."""
    y = flushed(y)
    if status[m] == OK and failed(y, limit[m]):
        status[m], failure_time[m] = BLEW_UP, t
        y = repeated(NAN, LIKE_Y)
    stored(samples, i * D, samples.shape[2], m, y)
    return y


@cuda.jit(device=True, inline="always")
def unchanged(y, p):
    return y


@cuda.jit(device=True, inline="always")
def into_pieces(y, p):
    return converted(to_pieces(*y, *p), LIKE_Y)  # noqa: F821 (the scene's, where it has one: the footer says)


@cuda.jit(device=True, inline="always")
def out_of_pieces(y, p):
    return converted(from_pieces(*y, *p), LIKE_Y)  # noqa: F821


entered, left = unchanged, unchanged  # a kernel file's footer makes them into_pieces, out_of_pieces where a scene
# has coordinates for its pieces


@cuda.jit(device=True, inline="always")
def runge_kutta_advance(h, t, y, p, factors):
    return rk_step(rhs, t, h, y, p, STAGES, WEIGHTS, STAGE_LOOP)


@cuda.jit(device=True, inline="always")
def no_factors(h, p):
    return ()


@cuda.jit(device=True, inline="always")
def splitting_advance(h, t, y, p, factors):
    return converted(split_step(h, y, p, factors), LIKE_Y)


@cuda.jit(device=True)
def runge_kutta_moved(t0, h, y0, p):
    """A member's step of h (s) from (t0, y0): the method's own path (ensemble.engine.events.located)."""
    return rk_step(rhs, REAL(t0), REAL(h), y0, p, STAGES, WEIGHTS, STAGE_LOOP)


@cuda.jit(device=True)
def splitting_moved(t0, h, y0, p):
    h = REAL(h)
    return left(converted(split_step(h, entered(y0, p), p, split_factors(h, p)), LIKE_Y), p)


@cuda.jit(device=True)
def adaptive_moved(t0, h, y0, p):
    t0, h = REAL(t0), REAL(h)
    return trial_step(rhs, t0, h, y0, p, converted(rhs(t0, *y0, *p), LIKE_Y), STAGES, STAGE_LOOP)[1]


@cuda.jit(device=True, inline="always")
def no_watch(events, g, t, h, y, new, p, status, failure_time, m):
    """A kernel without events: the step's new state."""
    return new, g


@cuda.jit(device=True, inline="always")
def event_watch(events, g, t, h, y, new, p, status, failure_time, m):
    """After member m's step of h (s) from t (s), from y to new (the family's coordinates), its events' signs g
    at the step's start (the CPU's watch: ensemble.engine.events.signs_chain): their signs at its end, and where
    one crossed, the member's values at both ends and its events located on the family's path (`moved`) and
    recorded (ensemble.engine.events.located); a member stopped at one gets status STOPPED, its time in
    failure_time (the launch counts its steps, then clears it) and a NaN state. Returns (state, the events' signs
    at the step's end)."""
    spec = events[0]
    after = SIGNS(t + h, left(new, p), p, levels_of(spec))
    hit, any_hit = repeated(False, g), False
    for e in range(E):
        crossing = crossed(g[e], after[e], 0.0, spec[e, 1])
        hit, any_hit = tuple_setitem(hit, e, crossing), any_hit or crossing
    if any_hit:
        y0, y1 = left(y, p), left(new, p)
        when = located(VALUES, moved, events, m, t, h, y0, p, VALUES(t, y0, p), VALUES(t + h, y1, p), hit)
        if when == when:
            status[m], failure_time[m] = STOPPED, when
            new = repeated(NAN, LIKE_Y)
    return new, after


watch, moved = no_watch, None  # an event kernel's footer binds event_watch and its family's moved


@cuda.jit(device=True, inline="always")
def fixed_frame(advance, prepared, state0, rate, h, steps_per_save, limit, samples, status, failure_time, works,
                start, m, events):
    """Member m from sample `start` on (0: from state0; later: from where the last call left works): each save
    interval's steps_per_save steps of h (s), advance(h, t, y, p, prepared(h, p)) taking it one step from t (s),
    the scene's coordinates for its pieces (`entered`, `left`) around them, and its events watched after each
    (`watch`; their signs carried in works rows D .. D + E - 1)."""
    p = converted(loaded(rate, 0, rate.shape[1], m, LIKE_P), LIKE_P)
    first = 0
    if start == 0:
        y = started(first_state(state0, m), limit, samples, status, failure_time, m)
        g = SIGNS(0.0, y, p, levels_of(events[0]))
        first = 1
    else:
        y = converted(loaded(works, 0, works.shape[1], m, WIDE_Y), LIKE_Y)
        g = loaded(works, D, works.shape[1], m, LIKE_G)
    factors = prepared(h, p)
    for i in range(first, samples.shape[0]):
        if status[m] == OK:
            y = entered(y, p)
            for step in range(steps_per_save):
                t = REAL(((start + i - 1) * steps_per_save + step) * h)
                y, g = watch(events, g, t, h, y, advance(h, t, y, p, factors), p, status, failure_time, m)
            y = left(y, p)
        y = saved(y, limit, samples, status, failure_time, i, m, (start + i) * steps_per_save * h)
    stored(works, 0, works.shape[1], m, converted(y, WIDE_Y))
    stored(works, D, works.shape[1], m, g)


@cuda.jit(fastmath=False, cache=True)
def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, works, start,
                       members, spec, times, counts, stopped, states):
    """state0, rate (D and P, members); limit (members,) -> samples (count, D, members) in REAL, status
    (members,), failure_time (members,; s, set only where a member fails); works (D + E, members); the events'
    arrays (ensemble.engine.events; placeholders in a kernel without events)."""
    m = cuda.grid(1)
    if m < members:
        fixed_frame(runge_kutta_advance, no_factors, state0, rate, REAL(h), steps_per_save, limit, samples, status,
                    failure_time, works, start, m, (spec, times, counts, stopped, states))


@cuda.jit(fastmath=False, cache=True)
def splitting_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, works, start, members,
                     spec, times, counts, stopped, states):
    """As runge_kutta_kernel: a step is the splitting's sequence (split_step), its pieces' factors computed once a
    call (split_factors)."""
    m = cuda.grid(1)
    if m < members:
        fixed_frame(splitting_advance, split_factors, state0, rate, REAL(h), steps_per_save, limit, samples, status,
                    failure_time, works, start, m, (spec, times, counts, stopped, states))


@cuda.jit(device=True, inline="always")
def first_guess(y, k0, rtol, atol, h, save_dt):
    """The first trial step: h (s) where it is > 0, else Hairer's guess from |y| and |y'| in tolerances
    (blocks.first_step)."""
    size, slope = ZERO, ZERO
    for c in range(D):
        size, slope = max(size, abs(y[c])), max(slope, abs(k0[c]))
    h = REAL(h)
    if h <= 0.0:
        scale = atol + rtol * size
        h = REAL(first_step(size / scale, slope / scale, save_dt))
    return h


@cuda.jit(device=True, inline="always")
def resumed(works, m):
    """Where the last call left an adaptive member: its state, first slopes, time, step, log2 of its last error,
    whether its last step was rejected, its counts, and its events' signs."""
    y = converted(loaded(works, 0, works.shape[1], m, WIDE_Y), LIKE_Y)
    k0 = converted(loaded(works, D, works.shape[1], m, WIDE_Y), LIKE_Y)
    time, h, log2_previous, rejected, accepted_count, rejected_count, evaluations = loaded(
        works, 2 * D, works.shape[1], m, WIDE_CONTROL)
    return (y, k0, REAL(time), REAL(h), REAL(log2_previous), 0.0 != rejected,
            (accepted_count, rejected_count, evaluations), loaded(works, 2 * D + 7, works.shape[1], m, LIKE_G))


@cuda.jit(fastmath=False, cache=True)
def adaptive_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, works, start,
                    members, spec, times, counts_of_events, stopped, states):
    """As runge_kutta_kernel, each member stepping to each saved time i save_dt (s) in trial steps its own
    controller sizes; control (3, members): first step (s; <= 0: guess it), rtol, atol -> counts (3, members):
    accepted, rejected, right-hand-side evaluations; works (2 D + 7 + E, members)."""
    m = cuda.grid(1)
    if m >= members:
        return
    p = converted(loaded(rate, 0, rate.shape[1], m, LIKE_P), LIKE_P)
    rtol, atol = REAL(control[1, m]), REAL(control[2, m])
    first = 0
    if start == 0:
        y = first_state(state0, m)
        k0 = converted(rhs(REAL(0.0), *y, *p), LIKE_Y)
        h = first_guess(y, k0, rtol, atol, control[0, m], save_dt)
        time, log2_previous, rejected_last = REAL(0.0), REAL(FIRST_LOG2_ERR_PREVIOUS), False
        tally = (0.0, 0.0, 1.0)  # accepted and rejected steps, right-hand-side evaluations
        y = started(y, limit, samples, status, failure_time, m)
        g = SIGNS(0.0, y, p, levels_of(spec))
        first = 1
    else:
        y, k0, time, h, log2_previous, rejected_last, tally, g = resumed(works, m)
    events = (spec, times, counts_of_events, stopped, states)
    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while status[m] == OK and time < target:
            step = min(h, REAL(target - time))
            t0 = time
            slopes, new = trial_step(rhs, REAL(time), step, y, p, k0, STAGES, STAGE_LOOP)
            err = error_norm(step, y, new, slopes, ERROR, rtol, atol)
            accepted, underflowed, h_next, log2_previous, time, tally = counted(
                err, step, h, log2_previous, rejected_last, time, target, tally, S - 1, CONTROLLER)
            h, rejected_last = REAL(h_next), not accepted  # h in REAL; time, as the controller's state, in float64
            if accepted:
                y, g = watch(events, g, t0, step, y, new, p, status, failure_time, m)
                k0 = slopes[S - 1]
            elif underflowed:
                status[m], failure_time[m] = UNDERFLOW, time
                y = repeated(NAN, LIKE_Y)
        y = saved(y, limit, samples, status, failure_time, i, m, target)
    stored(works, 0, works.shape[1], m, converted(y, WIDE_Y))
    stored(works, D, works.shape[1], m, converted(k0, WIDE_Y))
    stored(works, 2 * D, works.shape[1], m, converted((time, h, log2_previous, 1.0 if rejected_last else 0.0, *tally),
                                                      WIDE_CONTROL))
    stored(works, 2 * D + 7, works.shape[1], m, g)
    counts[0, m], counts[1, m], counts[2, m] = tally
