"""The field-of-sites CUDA kernels (ensemble.engine.gpu_sites): a chain's splitting, explicit Runge-Kutta and
embedded adaptive pair, one member to a thread's local arrays (T = 1) or to a block of T threads, each owning J
sites (thread `lane` owns sites lane, lane + T, ...), the positions in shared memory and the threads meeting at a
barrier after each kick and drift (each Runge-Kutta stage). Site q's position is x[q + 1]: x has a ghost site at
rest at each end (0 and N + 1); the ends of a ring are each other's neighbours. A kernel with events (one thread
to a member) watches them after each step with the member families' code (ensemble.engine.events).

A kernel's file is the GPU kernels' header (ensemble.engine.gpu.HEADER: REAL, NAN, TINY, ZERO, the scene's
`acceleration` as a device function, the step control), this module's imports, the names of the EXAMPLE section
below bound to the chain's sizes, layout and method, then the code from the CODE line on, unchanged
(gpu_sites.sites_kernel). As a module, the names are bound to an example, as ensemble.engine.sites_kernels's are:
4 unit masses between walls joined by unit springs, in float64, a thread to a member, Bogacki and Shampine's 3(2)
pair and Strang's kick-drift-kick.
"""
import math

from numba import cuda, float64

from ensemble.engine.blocks import FIRST_LOG2_ERR_PREVIOUS
from ensemble.engine.gpu import BLEW_UP, OK, STOPPED, UNDERFLOW
from ensemble.engine.gpu_device import device_events, device_helpers, device_tuples, device_unrolled
from ensemble.engine.sites import KICK

# ---------------------------------------------------------------- EXAMPLE: what a kernel file's header binds


@cuda.jit(device=True)
def acceleration(x_left, x, x_right, c_left, c_right):
    """The scene's acceleration (m s-2) of a site at x between neighbours at x_left and x_right."""
    return c_left * (x_left - x) + c_right * (x_right - x)


counted, first_step = device_helpers()
REAL = float64
NAN, TINY, ZERO = REAL(math.nan), REAL(2.2250738585072014e-308), REAL(0.0)
N, N2, D, PERIODIC = 4, 6, 8, False  # sites, positions with their ghosts, state values, a ring
T, J = 1, 4  # threads per member, sites per thread
S, SJ = 4, 16  # stages, stage slopes per thread
A = tuple(REAL(a) for a in (0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.75, 0.0, 0.0, 2 / 9, 1 / 3, 4 / 9, 0.0))
WEIGHTS = tuple(REAL(b) for b in (2 / 9, 1 / 3, 4 / 9, 0.0))
ERROR = tuple(REAL(e) for e in (2 / 9 - 7 / 24, 1 / 3 - 1 / 4, 4 / 9 - 1 / 3, -1 / 8))
CONTROLLER = (0.7 / 3 - 0.75 * 0.04, 0.04, 0.9, 0.2, 10.0)  # alpha, beta, safety, min_factor, max_factor
STAGE_LOOP = device_unrolled(S)  # a Runge-Kutta step's stages, written out: each stage's coefficients constants
SEQUENCE, FRACTIONS = (0, 1, 0), (REAL(0.5), REAL(1.0), REAL(0.5))  # piece numbers (KICK or drift), fractions
PIECE_LOOP = device_unrolled(len(SEQUENCE))  # a splitting's pieces, written out likewise
MERGED = True  # a step ends with the piece the next begins with (merged into one; never in an event kernel)
E, EVENT_ROWS = 0, (0,)  # events, and each one's row of the state (x; v): an event kernel's header binds them


@cuda.jit(device=True, inline="always")
def VALUES(t, y, p):
    """Each event's value (float64) in a member's state y (x; v) (2N,): gpu_device.device_event_values."""
    return ()

# ---------------------------------------------------------------- CODE: copied into every kernel's file
# Events (an event kernel: E > 0, one thread to a member, T = 1): after each step the watched rows' values are
# compared with those at its start; where one crossed, `located` (ensemble.engine.events, as the CPU's) finds it
# on the method's own step of s h from the step's start, kept in y0 before each step (`moved`: the step taken
# again from y0 into the member's arrays, its state copied out into y1), then the step is taken again as it was.
# The footer of an event kernel binds remember, watch_fixed, watch_adaptive, moved and family_step (a fixed step's);
# a kernel without events keeps the no_ ones, which are nothing.

_, _, _, repeated, tuple_setitem = device_tuples()
crossed, located = device_events()
LIKE_G = (0.0,) * E  # the events' values
STATE_COPY = 2 * N if E else 1  # a member's state (x; v), kept before each step where there are events


@cuda.jit(device=True)
def member():
    """This thread's member."""
    return cuda.blockIdx.x if T > 1 else cuda.grid(1)


@cuda.jit(device=True)
def lane():
    """This thread's place among its member's T threads."""
    return cuda.threadIdx.x if T > 1 else 0


@cuda.jit(device=True)
def sync():
    """A barrier for the member's threads (none for one thread)."""
    if T > 1:
        cuda.syncthreads()


@cuda.jit(device=True)
def neighbours(q):
    """Where in x site q's left and right neighbours are."""
    if PERIODIC:
        return N if q == 0 else q, 1 if q == N - 1 else q + 2
    return q, q + 2


@cuda.jit(device=True)
def failed(x, v, limit):
    """Whether any site of the chain is not finite or beyond `limit`; subnormals become zeros of their sign first,
    as the CPU's check_members makes them."""
    bad = 0
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] = x[q + 1] if abs(x[q + 1]) >= TINY else x[q + 1] * ZERO
            v[j] = v[j] if abs(v[j]) >= TINY else v[j] * ZERO
            if not (abs(x[q + 1]) <= limit and abs(v[j]) <= limit) or math.isinf(x[q + 1]) or math.isinf(v[j]):
                bad = 1
    return cuda.syncthreads_or(bad) if T > 1 else bad


@cuda.jit(device=True)
def fail(x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1], v[j] = NAN, NAN


@cuda.jit(device=True)
def store(samples, i, m, x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            samples[i, q, m], samples[i, N + q, m] = x[q + 1], v[j]


@cuda.jit(device=True)
def over_lanes(value, scratch, largest):
    """The sum (largest: the largest) of every thread's `value` >= 0 over the chain's threads, in lane order, in
    each of them (`value` itself for one thread)."""
    if T == 1:
        return value
    scratch[lane()] = value
    cuda.syncthreads()
    out = REAL(0.0)
    for t in range(T):
        out = max(out, scratch[t]) if largest else out + scratch[t]
    cuda.syncthreads()
    return out


@cuda.jit(device=True, inline="always")
def kept(x, v, y):
    """The member's state (x; v) into y (2N,); y."""
    for q in range(N):
        y[q], y[N + q] = x[q + 1], v[q]
    return y


@cuda.jit(device=True, inline="always")
def restarted(x, v, y):
    """The member's arrays x, v from its state y (x; v)."""
    for q in range(N):
        x[q + 1], v[q] = y[q], y[N + q]


@cuda.jit(device=True, inline="always")
def watched(x, v):
    """Each event's value (float64) in the member's arrays: row r < N site r's x, else site r - N's v."""
    g = repeated(0.0, LIKE_G)
    for e in range(E):
        r = EVENT_ROWS[e]
        g = tuple_setitem(g, e, float64(x[r + 1] if r < N else v[r - N]))
    return g


@cuda.jit(device=True, inline="always")
def watched_first(x, v, works, row, start, m):
    """The events' values at a call's start: in x, v at t = 0, else where the last call left them (works rows
    from `row`)."""
    if start == 0:
        return watched(x, v)
    g = repeated(0.0, LIKE_G)
    for e in range(E):
        g = tuple_setitem(g, e, works[row + e, m])
    return g


@cuda.jit(device=True, inline="always")
def crossings(before, after, spec):
    """(each event's crossed, whether any did): tuples of E values before and after a step."""
    hit, any_hit = repeated(False, LIKE_G), False
    for e in range(E):
        crossing = crossed(before[e], after[e], spec[e, 0], spec[e, 1])
        hit, any_hit = tuple_setitem(hit, e, crossing), any_hit or crossing
    return hit, any_hit


@cuda.jit(device=True, inline="always")
def no_remember(x, v, y):
    """A kernel without events: nothing kept before a step."""
    return y


@cuda.jit(device=True, inline="always")
def no_fixed_watch(advance, context, events, y0, y1, g, t, h, step, steps_per_save, status, failure_time, m, alive):
    return g, alive


@cuda.jit(device=True, inline="always")
def no_adaptive_watch(events, y1, g, t0, context, status, failure_time, m, alive):
    return g, alive


@cuda.jit(device=True, inline="always")
def fixed_watch(advance, context, events, y0, y1, g, t, h, step, steps_per_save, status, failure_time, m, alive):
    """After step `step` of h (s) from t (s), from the state kept in y0, of member m whose events had values g at
    its start: their values at its end, and where one crossed, the member's events located and recorded; a member
    stopped at one gets status STOPPED, its time in failure_time and a NaN state. Returns (values, alive)."""
    x, v = context[0], context[1]
    after = watched(x, v)
    hit, any_hit = crossings(g, after, events[0])
    if any_hit:
        when = located(VALUES, moved, events, m, t, h, y0, (context, y1), g, after, hit)
        restarted(x, v, y0)
        if when == when:
            status[m], failure_time[m] = STOPPED, when
            fail(x, v)
            return after, False
        advance(h, step, steps_per_save, context)  # the step again, as it was
    return after, alive


@cuda.jit(device=True, inline="always")
def adaptive_watch(events, y1, g, t0, context, status, failure_time, m, alive):
    """fixed_watch for an accepted trial step from t0 (s), its state in zx, zv (context: stage's, the trial
    step's), before it is accepted; a stopped member's state and trial state NaN."""
    h, x, v, zx, zv = context[0], context[1], context[2], context[3], context[4]
    after = watched(zx, zv)
    hit, any_hit = crossings(g, after, events[0])
    if any_hit:
        when = located(VALUES, moved, events, m, t0, h, y1, (context, y1), g, after, hit)
        if when == when:
            status[m], failure_time[m] = STOPPED, when
            fail(x, v)
            fail(zx, zv)
            return after, False
        STAGE_LOOP(stage, 1, A, context)  # the trial step again, as it was
    return after, alive


remember, watch_fixed, watch_adaptive, moved, family_step = no_remember, no_fixed_watch, no_adaptive_watch, None, None


@cuda.jit(device=True)
def kick(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            left, right = neighbours(q)
            v[j] += tau * acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
    sync()


@cuda.jit(device=True)
def drift(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] += tau * v[j]
    sync()


@cuda.jit(device=True, inline="always")
def piece(e, step, unused, context):
    """Piece e of a splitting's step `step` of a save interval: as on the CPU (sites.splitting_schedule), a step
    that ends with the piece the next begins with (verlet's half kicks) merges the two."""
    h, steps_per_save, x, v, cl, cr = context
    if MERGED and e == 0 and step > 0:
        return step
    tau = h * FRACTIONS[e]
    if MERGED and e == len(SEQUENCE) - 1:
        tau = tau + (h * FRACTIONS[0] if step < steps_per_save - 1 else REAL(0.0))
    if SEQUENCE[e] == KICK:
        kick(tau, x, v, cl, cr)
    else:
        drift(tau, x, v, cl, cr)
    return step


@cuda.jit(device=True, inline="always")
def stage(s, first, coefficients, context):
    """Runge-Kutta stage s (from stage `first` on): its state x + h sum_r coefficients[s S + r] k_r into zx, zv,
    then its slopes into kx, kv at s J + j (site q = lane + j T). Coefficients that are zero are left out."""
    h, x, v, zx, zv, kx, kv, cl, cr = context
    if s < first:
        return first
    for j in range(J):
        q = lane() + j * T
        if q < N:
            z, w = x[q + 1], v[j]
            for r in range(s):
                if coefficients[s * S + r] != 0.0:
                    z += (h * coefficients[s * S + r]) * kx[r * J + j]
                    w += (h * coefficients[s * S + r]) * kv[r * J + j]
            zx[q + 1], zv[j] = z, w
    sync()
    for j in range(J):
        q = lane() + j * T
        if q < N:
            left, right = neighbours(q)
            kx[s * J + j] = zv[j]
            kv[s * J + j] = acceleration(zx[left], zx[q + 1], zx[right], cl[j], cr[j])
    sync()  # every site's slopes read its neighbours' zx before the next stage writes it
    return first


@cuda.jit(device=True, inline="always")
def weighted(weights, k, j):
    """sum_s weights[s] k[s J + j] over the nonzero weights."""
    total = REAL(0.0)
    for s in range(S):
        if weights[s] != 0.0:
            total += weights[s] * k[s * J + j]
    return total


@cuda.jit(device=True, inline="always")
def loaded(x, v, cl, cr, state0, rate, works, start, m):
    """A chain's start: its sites' springs and state, from state0 (first call) or works (later calls)."""
    if lane() == 0:
        x[0], x[N + 1] = REAL(0.0), REAL(0.0)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            cl[j], cr[j] = REAL(rate[q, m]), REAL(rate[N + q, m])
            if start == 0:
                x[q + 1], v[j] = REAL(state0[q, m]), REAL(state0[N + q, m])
            else:
                x[q + 1], v[j] = REAL(works[q, m]), REAL(works[N + q, m])


@cuda.jit(device=True, inline="always")
def checked(alive, x, v, limit, samples, status, failure_time, i, m, t):
    """The end of a save interval at time t (s): a chain that runs (`alive`: the same in each of its threads) and
    has failed stops (status BLEW_UP, its state NaN); sample i stored. Whether it still runs."""
    if alive and failed(x, v, limit[m]):
        alive = False
        if lane() == 0:
            status[m], failure_time[m] = BLEW_UP, t
        fail(x, v)
    store(samples, i, m, x, v)
    return alive


@cuda.jit(device=True, inline="always")
def fixed_frame(advance, context, state0, rate, h, steps_per_save, limit, samples, status, failure_time, works,
                start, m, events, y0, y1):
    """A fixed-step kernel's member m from sample `start` on: advance(h, step, steps_per_save, context) takes it
    one step; context begins with its x, v, cl and cr. Its events (if any) watched after each step."""
    x, v, cl, cr = context[0], context[1], context[2], context[3]
    alive = status[m] == OK
    loaded(x, v, cl, cr, state0, rate, works, start, m)
    sync()
    g = watched_first(x, v, works, 2 * N, start, m)
    first = 0
    if start == 0:
        alive = checked(alive, x, v, limit, samples, status, failure_time, 0, m, 0.0)  # a start beyond its limit
        first = 1
    for i in range(first, samples.shape[0]):
        for step in range(steps_per_save):
            if alive:
                y0 = remember(x, v, y0)
                advance(h, step, steps_per_save, context)
                g, alive = watch_fixed(advance, context, events, y0, y1, g, ((start + i - 1) * steps_per_save + step)
                                       * h, h, step, steps_per_save, status, failure_time, m, alive)
        alive = checked(alive, x, v, limit, samples, status, failure_time, i, m, (start + i) * steps_per_save * h)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m] = x[q + 1], v[j]
    for e in range(E):
        works[2 * N + e, m] = g[e]


@cuda.jit(device=True, inline="always")
def fixed_moved(t0, h, y0, p):
    """A member's step of h (s) (the family's, `family_step`) from its state y0 (x; v) (events.located's advance;
    p: (context, y1)): its new state, in y1."""
    context, y1 = p
    restarted(context[0], context[1], y0)
    family_step(REAL(h), 0, 1, context)
    return kept(context[0], context[1], y1)


@cuda.jit(device=True, inline="always")
def adaptive_moved(t0, h, y0, p):
    """As fixed_moved, the pair's trial step of h from the state in x, v (its last stage state: FSAL)."""
    (_, x, v, zx, zv, kx, kv, cl, cr), y1 = p
    STAGE_LOOP(stage, 1, A, (REAL(h), x, v, zx, zv, kx, kv, cl, cr))
    return kept(zx, zv, y1)


@cuda.jit(device=True, inline="always")
def split_step(h, step, steps_per_save, context):
    x, v, cl, cr = context
    PIECE_LOOP(piece, step, None, (h, steps_per_save, x, v, cl, cr))


@cuda.jit(device=True, inline="always")
def runge_kutta_step(h, step, steps_per_save, context):
    x, v, cl, cr, zx, zv, kx, kv = context
    STAGE_LOOP(stage, 0, A, (h, x, v, zx, zv, kx, kv, cl, cr))
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] += h * weighted(WEIGHTS, kx, j)
            v[j] += h * weighted(WEIGHTS, kv, j)


@cuda.jit(fastmath=False, cache=True)
def splitting_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, works, start, members,
                     spec, times, counts, stopped, states):
    """state0, rate (2N, members); limit (members,) -> samples (count, 2N, members) in REAL, status (members,),
    failure_time (members,; s, set only where a member fails); works (2N + E, members): where a call leaves each
    member for the next; spec .. states: its events' (ensemble.engine.events; empty where it has none)."""
    m = member()
    if m >= members:
        return
    x = cuda.shared.array(N2, REAL) if T > 1 else cuda.local.array(N2, REAL)
    context = (x, cuda.local.array(J, REAL), cuda.local.array(J, REAL), cuda.local.array(J, REAL))
    fixed_frame(split_step, context, state0, rate, REAL(h), steps_per_save, limit, samples, status, failure_time,
                works, start, m, (spec, times, counts, stopped, states), cuda.local.array(STATE_COPY, REAL),
                cuda.local.array(STATE_COPY, REAL))


@cuda.jit(fastmath=False, cache=True)
def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, works, start,
                       members, spec, times, counts, stopped, states):
    """As splitting_kernel, for the tableau A (flat S x S), WEIGHTS: the stage state zx (shared by the chain's
    threads) and zv, and the stage slopes kx, kv (S J each) of this thread's sites."""
    m = member()
    if m >= members:
        return
    x = cuda.shared.array(N2, REAL) if T > 1 else cuda.local.array(N2, REAL)
    zx = cuda.shared.array(N2, REAL) if T > 1 else cuda.local.array(N2, REAL)
    if lane() == 0:
        zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)
    context = (x, cuda.local.array(J, REAL), cuda.local.array(J, REAL), cuda.local.array(J, REAL), zx,
               cuda.local.array(J, REAL), cuda.local.array(SJ, REAL), cuda.local.array(SJ, REAL))
    fixed_frame(runge_kutta_step, context, state0, rate, REAL(h), steps_per_save, limit, samples, status,
                failure_time, works, start, m, (spec, times, counts, stopped, states),
                cuda.local.array(STATE_COPY, REAL), cuda.local.array(STATE_COPY, REAL))


@cuda.jit(device=True, inline="always")
def first_guess(x, v, cl, cr, kx, kv, scratch, rtol, atol, h, save_dt):
    """The first slopes into kx, kv, and the first trial step: h (s) where it is > 0, else Hairer's guess from |y|
    and |y'| in tolerances (blocks.first_step), taken over the chain's threads (all then choose the same step)."""
    size, slope = REAL(0.0), REAL(0.0)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            left, right = neighbours(q)
            kx[j], kv[j] = v[j], acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
            size = max(size, abs(x[q + 1]) / (atol + rtol * abs(x[q + 1])), abs(v[j]) / (atol + rtol * abs(v[j])))
            slope = max(slope, abs(v[j]) / (atol + rtol * abs(x[q + 1])), abs(kv[j]) / (atol + rtol * abs(v[j])))
    size, slope = over_lanes(size, scratch, True), over_lanes(slope, scratch, True)
    h = REAL(h)
    if h <= 0.0:
        h = REAL(first_step(size, slope, save_dt))
    return h


@cuda.jit(device=True, inline="always")
def error_norm(step, x, v, zx, zv, kx, kv, scratch, rtol, atol):
    """A trial step's error norm: the root mean square of step sum_s ERROR[s] k_s over the chain's D values, each
    scaled by atol + rtol max(|y|, |new y|)."""
    estimate = REAL(0.0)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            qx = step * weighted(ERROR, kx, j) / (atol + rtol * max(abs(x[q + 1]), abs(zx[q + 1])))
            qv = step * weighted(ERROR, kv, j) / (atol + rtol * max(abs(v[j]), abs(zv[j])))
            estimate += qx * qx + qv * qv
    return math.sqrt(over_lanes(estimate, scratch, False) / D)


@cuda.jit(device=True, inline="always")
def accept(x, v, zx, zv, kx, kv):
    """The trial state zx, zv becomes the state, its last stage's slopes the next step's first (FSAL)."""
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1], v[j] = zx[q + 1], zv[j]
            kx[j], kv[j] = kx[(S - 1) * J + j], kv[(S - 1) * J + j]


@cuda.jit(device=True, inline="always")
def resumed(works, kx, kv, m):
    """Where the last call left a member: its first slopes into kx, kv; its time, step, the controller's memory,
    whether its last step was rejected, and its counts."""
    for j in range(J):
        q = lane() + j * T
        if q < N:
            kx[j], kv[j] = REAL(works[2 * N + q, m]), REAL(works[3 * N + q, m])
    return (REAL(works[4 * N, m]), REAL(works[4 * N + 1, m]), REAL(works[4 * N + 2, m]), 0.0 != works[4 * N + 3, m],
            (works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m]))


@cuda.jit(device=True, inline="always")
def left(works, counts, m, x, v, kx, kv, controller, tally):
    """Where this call leaves a member for the next (resumed), and its counts: controller (time, h, log2 of the
    last error, rejected last), tally (accepted, rejected, right-hand-side evaluations)."""
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m], works[2 * N + q, m], works[3 * N + q, m] = x[q + 1], v[j], kx[j], kv[j]
    if lane() == 0:
        works[4 * N, m], works[4 * N + 1, m], works[4 * N + 2, m] = controller[0], controller[1], controller[2]
        works[4 * N + 3, m] = 1.0 if controller[3] else 0.0
        works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m] = tally[0], tally[1], tally[2]
        counts[0, m], counts[1, m], counts[2, m] = tally[0], tally[1], tally[2]


@cuda.jit(fastmath=False, cache=True)
def adaptive_kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, works, start,
                    members, spec, times, counts_of_events, stopped, states):
    """As splitting_kernel, each member stepping to each saved time i save_dt (s) in trial steps its own controller
    sizes; control (3, members): first step (s; <= 0: guess it), rtol, atol -> counts (3, members): accepted,
    rejected, right-hand-side evaluations; works (4N + 7 + E, members)."""
    m = member()
    if m >= members:
        return
    x = cuda.shared.array(N2, REAL) if T > 1 else cuda.local.array(N2, REAL)
    zx = cuda.shared.array(N2, REAL) if T > 1 else cuda.local.array(N2, REAL)
    scratch = cuda.shared.array(T, REAL) if T > 1 else cuda.local.array(T, REAL)  # over_lanes's
    v, cl, cr, zv = (cuda.local.array(J, REAL), cuda.local.array(J, REAL), cuda.local.array(J, REAL),
                     cuda.local.array(J, REAL))
    kx, kv = cuda.local.array(SJ, REAL), cuda.local.array(SJ, REAL)  # stage s's slopes at s J + j
    rtol, atol = REAL(control[1, m]), REAL(control[2, m])
    alive = status[m] == OK
    if lane() == 0:
        zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)
    loaded(x, v, cl, cr, state0, rate, works, start, m)
    sync()
    g, y1 = watched_first(x, v, works, 4 * N + 7, start, m), cuda.local.array(STATE_COPY, REAL)
    events = (spec, times, counts_of_events, stopped, states)
    first = 0
    if start == 0:
        h = first_guess(x, v, cl, cr, kx, kv, scratch, rtol, atol, control[0, m], save_dt)
        time, log2_previous, rejected_last = REAL(0.0), REAL(FIRST_LOG2_ERR_PREVIOUS), False
        tally = (0.0, 0.0, 1.0)  # accepted and rejected steps, right-hand-side evaluations
        alive = checked(alive, x, v, limit, samples, status, failure_time, 0, m, 0.0)  # a start beyond its limit
        first = 1
    else:
        time, h, log2_previous, rejected_last, tally = resumed(works, kx, kv, m)
    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while alive and time < target:
            step, t0 = min(h, REAL(target - time)), time
            STAGE_LOOP(stage, 1, A, (step, x, v, zx, zv, kx, kv, cl, cr))  # FSAL: stage 0 is the last step's last
            err = error_norm(step, x, v, zx, zv, kx, kv, scratch, rtol, atol)
            accepted, underflowed, h_next, log2_previous, time, tally = counted(
                err, step, h, log2_previous, rejected_last, time, target, tally, S - 1, CONTROLLER)
            h, rejected_last = REAL(h_next), not accepted  # h in REAL; time, as the controller's state, in float64
            if accepted:
                g, alive = watch_adaptive(events, y1, g, t0, (step, x, v, zx, zv, kx, kv, cl, cr), status,
                                          failure_time, m, alive)
            if accepted and alive:
                accept(x, v, zx, zv, kx, kv)
            elif underflowed:
                alive = False
                if lane() == 0:
                    status[m], failure_time[m] = UNDERFLOW, time
                fail(x, v)
        alive = checked(alive, x, v, limit, samples, status, failure_time, i, m, target)
    left(works, counts, m, x, v, kx, kv, (time, h, log2_previous, rejected_last),
         tally)
    for e in range(E):
        works[4 * N + 7 + e, m] = g[e]
