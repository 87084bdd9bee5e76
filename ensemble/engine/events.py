"""Events: the times at which a function of a member's state crosses a level, each located within its step, and
members that stop at one. Written once for the member families on both devices: the CPU's frames
(ensemble.engine.frames) call the watchers here around a family's steps, and a GPU thread (gpu_kernels.event_watch)
calls `crossed` and `located` as device functions; a CPU kernel without events calls NO_BEGIN, NO_REMEMBER
(NO_LEVELS, NO_ADAPTIVE_WATCH), which are nothing, and NO_STEPS, a loop of steps alone.

An event's value is a function value(t, y, p) -> float of a member's time (s), state and parameters (tuples):
a state component, a scene's observable, or a scene's own event function (`component`, `function_value`). A
kernel with E events watches them all at the end of every step through their signs, `signs(t, y, p, levels)` -> E
floats (`signs_chain`), each of the sign of the value's difference from its level: that difference, or a scene's
watch of the observable, a function of that sign that costs less (the top's tilt: |w| sin(tilt - level), without
the arctangent's divisions), and compares them with their signs at the step's start. Where one crossed in its
direction, the member's values at both ends are computed and the crossing is found on the method's own path
through the step: the state at t0 + s h is the method's step of s h from the step's start (t0, y0), `advance(t0,
s h, y0, p)` (each family's advance_of), by the Illinois variant of regula falsi, to the last bits of the step's
time. The event's time is then as accurate as the method's states, for every family: an interpolant of the step's
ends would not be (a cubic Hermite is of order 3, dopri5's dense output of order 4, below the methods' own). A
GPU thread watches its member's events through the same signs (gpu_device.device_event_signs).

A kernel call's events are a tuple (spec, times, counts, stopped, states):
- spec (E, 5): per event its level, direction (+1 up: from below to level or above; -1 down; 0 both), stop
  (1: the member stops at its first occurrence), count (occurrences kept) and keep (1: its state at each kept
  occurrence goes to `states`);
- times (E, count, members), s: the first `count` occurrences of each event per member (count: the largest),
  NaN where fewer occurred (filled by the caller);
- counts (E, members): every occurrence so far, kept or not (floats);
- stopped (D, members): a stopped member's state at its event, in the scene's coordinates (NaN elsewhere; a
  (D, 1) placeholder where no event stops a member);
- states (E, count, D, members): the state at each kept occurrence of an event that keeps it, in the scene's
  coordinates (NaN where none; a (E, 1, D, 1) placeholder where no event keeps it).
A stopped member's status is STOPPED (results.Status.STOPPED_BY_EVENT), its state NaN after its event, so that
its later samples are NaN and its block's steps carry it as they carry a failed member.

Work rows from a kernel's `first` event row: fixed steps keep the signs at the step's end and start and the
state at its start (`fixed_watcher`); adaptive kernels the signs at the step's start (E rows, which the watch moves
to the trial's where its step is accepted; the step's states are in rows 0 and NEW).
"""
from __future__ import annotations

from functools import cache

import numpy as np
from numba import float64, njit
from numba.cpython.unsafe.tuple import tuple_setitem

from ..results import Status
from .blocks import ERR, FAST, REJECTED_LAST, STEP, TIME, H, select
from .tuples import converted, loaded, repeated, stored

STOPPED = int(Status.STOPPED_BY_EVENT)
ROOT_ITERATIONS = 80  # Illinois steps at most; it converges superlinearly, in a dozen for a smooth crossing
NOT_CROSSED = 2.0  # `root`'s fraction of a step where the event did not cross in it
WATCH_ROUNDING = 1e-5  # how close to its level (relative) a value may be where a scene's watch says otherwise


def _inlined(function):
    return njit(inline="always", **FAST)(function)


@cache
def component(k: int, compiled=_inlined):
    """value(t, y, p) = y[k]: a state component."""
    def value(t, y, p):
        return float64(y[k])  # a float64 in a GPU's float32 kernel too (float() keeps a float32)
    return compiled(value)


@cache
def function_value(function, index: int, compiled=_inlined, counts: tuple | None = None):
    """value(t, y, p) = function(t, *y, *p), or its value `index` where index >= 0 (a vector observable); with
    counts (D, P), the call written out (`written_out`)."""
    if counts:
        return written_out(function, counts, "", index, compiled)
    if index < 0:
        def value(t, y, p):
            return float64(function(t, *y, *p))
    else:
        def value(t, y, p):
            return float64(function(t, *y, *p)[index])
    return compiled(value)


@cache
def written_out(function, counts: tuple, rest: str, index: int, compiled=_inlined):
    """call(t, y, p<rest>) = function(t, y[0], .., y[D - 1], p[0], .., p[P - 1]<rest>) as a float64 (its value
    `index` where index >= 0), counts = (D, P): a call that Numba inlines where `function` is compiled to be
    inlined (it inlines no call with *args). The kernels' watch calls a scene's functions so (kernels.event_signs):
    through *args, LLVM inlined them only later, and the watch's loop it left cost rk4 eight points of its rate
    more than the same arithmetic on a state row."""
    D, P = counts
    arguments = ", ".join(["t", *(f"y[{i}]" for i in range(D)), *(f"p[{i}]" for i in range(P))]) + rest
    picked = f"[{index}]" if index >= 0 else ""
    namespace = {"function": function, "float64": float64}
    exec(f"def call(t, y, p{rest}):\n    return float64(function({arguments}){picked})\n", namespace)
    return compiled(namespace["call"])


@cache
def values_chain(functions: tuple, compiled=_inlined):
    """values(t, y, p) -> (functions[0](t, y, p), functions[1](t, y, p), ..): every event's value, written out."""
    if not functions:
        def values(t, y, p):
            return ()
        return compiled(values)
    previous, last = values_chain(functions[:-1], compiled), functions[-1]

    def values(t, y, p):
        return previous(t, y, p) + (last(t, y, p),)
    return compiled(values)


@cache
def difference(value, compiled=_inlined):
    """sign(t, y, p, level) = value(t, y, p) - level: its sign says on which side of the level the value is (the
    difference of two floats is 0 only where they are equal, and negative only where the first is less)."""
    def sign(t, y, p, level):
        return value(t, y, p) - level
    return compiled(sign)


@cache
def function_sign(function, index: int, compiled=_inlined, counts: tuple | None = None):
    """sign(t, y, p, level) = function(t, *y, *p, level), or its value `index` where index >= 0: a scene's watch
    of an observable (EVENT_VALUES' third entry), of the sign of the observable's difference from the level; with
    counts (D, P), the call written out (`written_out`)."""
    if counts:
        return written_out(function, counts, ", level", index, compiled)
    if index < 0:
        def sign(t, y, p, level):
            return float64(function(t, *y, *p, level))
    else:
        def sign(t, y, p, level):
            return float64(function(t, *y, *p, level)[index])
    return compiled(sign)


@cache
def signs_chain(functions: tuple, compiled=_inlined):
    """signs(t, y, p, levels) -> (functions[0](t, y, p, levels[0]), ..): every event's sign (`difference`,
    `function_sign`), written out."""
    if not functions:
        def signs(t, y, p, levels):
            return ()
        return compiled(signs)
    previous, last, e = signs_chain(functions[:-1], compiled), functions[-1], len(functions) - 1

    def signs(t, y, p, levels):
        return previous(t, y, p, levels) + (last(t, y, p, levels[e]),)
    return compiled(signs)


def source_value(source: tuple, function_of, compiled=_inlined, counts: tuple | None = None):
    """value(t, y, p) of an event's source (results.Event.source): ("state", k), the state's value k; ("function",
    name, index[, watch]), the scene's function function_of(name) (compiled as the kernel's), its value `index`
    if index >= 0 (counts: function_value's)."""
    if source[0] == "state":
        return component(source[1], compiled)
    return function_value(function_of(source[1]), source[2], compiled, counts)


def values_of(sources: tuple, function_of, compiled=_inlined):
    """values_chain of events' sources (`source_value`)."""
    return values_chain(tuple(source_value(source, function_of, compiled) for source in sources), compiled)


def signs_of(sources: tuple, function_of, compiled=_inlined, counts: tuple | None = None):
    """signs_chain of events' sources: the scene's watch where a function source names one (its fourth entry),
    function_of(name); else the difference of the source's value (`source_value`) from the level. counts (D, P):
    the scene's functions are called written out (`written_out`), function_of's compiled to be inlined."""
    watches = (source[3] if source[0] == "function" and len(source) > 3 else None for source in sources)
    return signs_chain(tuple(function_sign(function_of(watch), source[2], compiled, counts) if watch else
                             difference(source_value(source, function_of, compiled, counts), compiled)
                             for source, watch in zip(sources, watches)), compiled)


EVENT_STATE = ("event_times", "event_counts", "stopped", "event_states")  # what a run's events carry on


def event_spec(events: tuple) -> np.ndarray:
    """The kernels' spec of events (results.Event), (E, 5): level, direction, stop, count, keep (above)."""
    return np.array([(e.level, e.sign, float(e.stop), e.count, float(bool(e.keep))) for e in events]).reshape(-1, 5)


def start_values(events: tuple, state_rows: int, members: int) -> dict[str, tuple[tuple[int, ...], float]]:
    """Each EVENT_STATE array's (shape, value) at a run's start (above): no times (NaN), no counts, no stopped
    states, no kept states; the stopped states of one member where no event stops one, and the kept states of
    one where no event keeps them (the kernel's argument types are the same; a 10^7-top run had 240 MB of stopped
    states it never wrote)."""
    E, kept = len(events), max(e.count for e in events)
    stopped = (state_rows, members) if any(e.stop for e in events) else (state_rows, 1)
    states = (E, kept, state_rows, members) if any(e.keep for e in events) else (E, 1, state_rows, 1)
    return {"event_times": ((E, kept, members), np.nan), "event_counts": ((E, members), 0.0),
            "stopped": (stopped, np.nan), "event_states": (states, np.nan)}


def started(events: tuple, state_rows: int, members: int) -> dict[str, np.ndarray]:
    """The EVENT_STATE arrays of `events` at a run's start (float64; start_values)."""
    return {name: np.full(shape, value) for name, (shape, value) in start_values(events, state_rows, members).items()}


# ---------------------------------------------------------------- one member's crossings

@njit(inline="always", **FAST)
def crossed(before, after, level, direction):
    """Whether a value went from `before` to `after` across `level` in `direction` (+1 up, -1 down, 0 either):
    up from below to the level or above, down from above to the level or below (a value resting on the level
    crosses once). False for NaN."""
    up = (before < level) & (after >= level)
    down = (before > level) & (after <= level)
    return (up & (direction >= 0.0)) | (down & (direction <= 0.0))


@njit(inline="always", **FAST)
def straddles(before, after, level):
    """Whether `before` and `after` lie on both sides of `level`, or one on it: every crossing `crossed` finds, in
    either direction, and some it does not (a product that underflows): the watch's test after every step, two
    operations cheaper, which `locate` narrows member by member with `crossed`. False for NaN."""
    return (before - level) * (after - level) <= 0.0


@njit(inline="always", **FAST)
def any_straddles(before, after):
    """Whether any of E signs (a tuple; `straddles` of 0) changed or is 0."""
    hit = False
    for e in range(len(before)):
        hit |= straddles(before[e], after[e], 0.0)
    return hit


@njit(inline="always", **FAST)
def user_state(to_user, y, p):
    """A member's state in the scene's coordinates (a splitting's from_pieces, or None: as it is)."""
    if to_user is None:
        return y
    return converted(to_user(*y, *p), y)


@njit(inline="always", **FAST)  # inlined: a function handed to a call of its own makes a kernel uncacheable
def root(values, advance, e, level, t0, h, y0, p, before, after, iterations=ROOT_ITERATIONS):
    """The fraction s of a step of h (s) from t0 (s) and state y0 at which event e's value on the method's path
    (advance) reaches `level`, its values at the ends before and after on either side of it: Illinois regula
    falsi, `iterations` steps at most (with none, 1 wherever it finds a crossing within the step). Where they are
    not (a scene's watch saw a crossing its value does not show), the nearer end if its value is on the level to
    rounding (within WATCH_ROUNDING of it, relative: a hundred float32 roundings), else NOT_CROSSED (a watch's 0
    where the value is off the level: the top's at rest, or its squares underflowed)."""
    a, b, ga, gb = 0.0, 1.0, before - level, after - level
    if gb == 0.0:
        return 1.0
    if not ((ga < 0.0) != (gb < 0.0)):
        near, value = (0.0, before) if abs(ga) <= abs(gb) else (1.0, after)
        return near if abs(value - level) <= WATCH_ROUNDING * max(abs(level), abs(value)) else NOT_CROSSED
    side = 0
    s = 1.0
    for _ in range(iterations):
        s = (a * gb - b * ga) / (gb - ga)
        if not (a < s < b):
            s = 0.5 * (a + b)
        if not (a < s < b):
            break  # a and b are neighbouring floats
        g = values(t0 + s * h, advance(t0, s * h, y0, p), p)[e] - level
        if g == 0.0:
            return s
        if (g > 0.0) == (gb > 0.0):
            b, gb = s, g
            if side == 1:
                ga *= 0.5
            side = 1
        else:
            a, ga = s, g
            if side == -1:
                gb *= 0.5
            side = -1
        if b - a <= 1e-15:
            break
    return b  # the first point known to have crossed


@njit(inline="always", **FAST)
def located(values, advance, arrays, member, t0, h, y0, p, before, after, hit):
    """Every event of one member that crossed within its step of h (s) from t0 (s) and state y0 (before, after:
    each event's values at the step's ends, tuples of E; hit: whether each crossed, `crossed_each` of its values or
    of its watch's signs), located on the method's path `advance` (`root`) and
    recorded in the kernel call's event arrays (times, counts, and states where an event keeps them), but those
    after the step's first stopping event, at which the member's state goes to `stopped`. Returns the stopping
    time (s), or NaN where the member goes on. An occurrence past an event's `count` in a step where no event that
    stops the member crossed is counted without being located (`root` without iterations: its time is not kept,
    and no stop comes before it). The CPU's kernels (`locator`) and the GPU's (gpu_kernels) call it."""
    spec, times, counts, stopped, states = arrays
    D, kept_most = stopped.shape[0], times.shape[1]
    fractions = repeated(NOT_CROSSED, before)
    stop = NOT_CROSSED
    stopping = False  # whether an event that stops the member crossed: then every crossing's time is needed
    for e in range(len(before)):
        stopping |= hit[e] and spec[e, 2] > 0.0
    for e in range(len(before)):
        if hit[e]:
            needed = stopping or counts[e, member] < spec[e, 3]  # else counted alone: 1 where it crossed
            fraction = root(values, advance, e, spec[e, 0], t0, h, y0, p, before[e], after[e],
                            ROOT_ITERATIONS if needed else 0)
            fractions = tuple_setitem(fractions, e, fraction)
            if spec[e, 2] > 0.0:
                stop = min(stop, fraction)
    for e in range(len(before)):
        if fractions[e] <= min(stop, 1.0):
            kept = int(counts[e, member])
            if kept < spec[e, 3]:
                times[e, kept, member] = t0 + fractions[e] * h
                if spec[e, 4] > 0.0:
                    stored(states, (e * kept_most + kept) * D, states.shape[3], member,
                           advance(t0, fractions[e] * h, y0, p))
            counts[e, member] += 1.0
    if stop > 1.0:
        return np.nan
    stored(stopped, 0, stopped.shape[1], member, advance(t0, stop * h, y0, p))
    return t0 + stop * h


@cache
def locator(values, advance):
    """located(arrays, member, t0, h, y0, p, before, after, hit) for a CPU event kernel of `values` and a family's
    `advance` (`located`'s, bound). A function of its own, called where an event occurred: inlined into the
    members' loop, it tripled the kernel's compile time; so is the family's step it calls (`moved`), compiled once
    rather than at each of its three calls."""
    @njit(**FAST)
    def moved(t0, h, y0, p):
        return advance(t0, h, y0, p)

    @njit(**FAST)
    def located_here(arrays, member, t0, h, y0, p, before, after, hit):
        return located(values, moved, arrays, member, t0, h, y0, p, before, after, hit)
    return located_here


@njit(inline="always", **FAST)
def any_crossed(before, after, levels, directions):
    """Whether any event crossed (`crossed`): tuples of E values each, E a constant (the loop is written out)."""
    hit = False
    for e in range(len(before)):
        hit |= crossed(before[e], after[e], levels[e], directions[e])
    return hit


@njit(inline="always", **FAST)
def crossed_each(before, after, levels, directions):
    """Whether each event crossed (`crossed`): a tuple of E booleans, of tuples of E values each."""
    hit = repeated(False, before)
    for e in range(len(before)):
        hit = tuple_setitem(hit, e, crossed(before[e], after[e], levels[e], directions[e]))
    return hit


@njit(inline="always", **FAST)
def levels_and_directions(spec, like_g):
    """spec's levels and directions as tuples shaped like like_g (E values): constants of a block's loops, which
    LLVM need not load again after each store into the work array."""
    columns = spec.shape[1]
    return loaded(spec, 0, columns, 0, like_g), loaded(spec, 0, columns, 1, like_g)


# ---------------------------------------------------------------- the frames' calls


@njit(inline="always", **FAST)
def NO_BEGIN(like_y, like_p, work, B, context):
    """A kernel without events: nothing at the start."""


@njit(inline="always", **FAST)
def NO_REMEMBER(work, B, j, y):
    """A fixed-step kernel without events: nothing kept of a member's step."""


@njit(inline="always", **FAST)
def NO_STEPS(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, context):
    """A fixed-step kernel without events: save interval i's steps_per_save steps of h (s) of a block of B
    members, members_step(like_y, like_p, work, B, h, t, remember) taking each one step from t (s)."""
    for n in range(steps_per_save):
        members_step(like_y, like_p, work, B, h, ((i - 1) * steps_per_save + n) * h, remember)


@njit(inline="always", **FAST)
def watched_steps(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, watch, locate, levels,
                  context):
    """NO_STEPS with events: after each step, watch says whether any member's events crossed their levels (a
    tuple), and where any did, the loop of steps stops for `locate` to find them, then goes on (a call in that
    loop, even one never made, cost a chain's verlet a third of its rate, and a top's rk4 a tenth)."""
    n = 0
    while n < steps_per_save:
        hits = False
        while not hits and n < steps_per_save:
            members_step(like_y, like_p, work, B, h, ((i - 1) * steps_per_save + n) * h, remember)
            n += 1
            hits = watch(like_y, like_p, work, B, ((i - 1) * steps_per_save + n) * h, levels, context)
        if hits:
            locate(like_y, like_p, work, B, ((i - 1) * steps_per_save + n - 1) * h, h, context)


@njit(inline="always", **FAST)
def NO_LEVELS(context):
    """An adaptive kernel without events: no levels."""
    return ()


@njit(inline="always", **FAST)
def NO_ADAPTIVE_WATCH(like_y, like_p, work, B, K, NEW, C0, S, levels, context):
    """An adaptive kernel without events: nothing after a step's control."""


@cache
def beginning(signs, first: int, E: int):
    """begin(like_y, like_p, work, B, context) for either watcher: every member's events' signs (`signs_chain`) at
    t = 0 into its rows from `first` (the signs at the first step's start)."""
    like_g = (0.0,) * E

    @njit(inline="always", **FAST)
    def begin(like_y, like_p, work, B, context):
        D = len(like_y)
        levels, _ = levels_and_directions(context[0][0], like_g)
        for j in range(B):
            y, p = loaded(work, 0, B, j, like_y), loaded(work, D, B, j, like_p)
            stored(work, first, B, j, signs(0.0, y, p, levels))
    return begin


def fixed_rows(first: int, E: int) -> tuple[int, int, int]:
    """A fixed-step kernel's event rows from `first` (fixed_watcher): G (E), CROSSED (1) and OLD (D)."""
    return first, first + E, first + E + 1


def fixed_locate(values, signs, advance, to_user, first: int, E: int):
    """fixed_watcher's locate(like_y, like_p, work, B, t, h, context), rows as there: which members crossed in the
    step from t (s) of h (s), in a loop over the block that vectorizes (one loop that also called `located` was
    scalar), then each of those located."""
    located, like_g = locator(values, advance), (0.0,) * E
    G, CROSSED, OLD = fixed_rows(first, E)

    @njit(inline="always", **FAST)
    def locate(like_y, like_p, work, B, t, h, context):
        arrays, status, failure_time, j0 = context
        D = len(like_y)
        levels, directions = levels_and_directions(arrays[0], like_g)
        zeros = repeated(0.0, like_g)
        for j in range(B):
            p = loaded(work, D, B, j, like_p)
            before = signs(t, user_state(to_user, loaded(work, OLD, B, j, like_y), p), p, levels)
            work[CROSSED * B + j] = select(any_crossed(before, loaded(work, G, B, j, like_g), zeros, directions),
                                           1.0, 0.0)
        for j in range(B):
            if work[CROSSED * B + j] != 0.0:
                p = loaded(work, D, B, j, like_p)
                y0 = user_state(to_user, loaded(work, OLD, B, j, like_y), p)
                before, after = signs(t, y0, p, levels), loaded(work, G, B, j, like_g)  # as the last watch had them
                y1 = user_state(to_user, loaded(work, 0, B, j, like_y), p)
                when = located(arrays, j0 + j, t, h, y0, p, values(t, y0, p), values(t + h, y1, p),
                               crossed_each(before, after, zeros, directions))
                if when == when:
                    stop_member(work, 0, D, B, j, status, failure_time, j0, when)
    return locate


def fixed_watcher(values, signs, advance, to_user, first: int, E: int):
    """(begin, remember, steps) for a fixed-step kernel (ensemble.engine.frames.fixed_step) whose E events' rows
    start at `first`: their signs (`signs_chain`: the sign of each value's difference from its level, or of a
    scene's cheaper watch of it) at the last step's end (E rows), whether each member crossed in the step just
    located (1 row) and the state at the step's start (D rows). Levels are read once a save interval (`steps`),
    and what a watch makes of them (the top's cos, sin) there.

    begin(like_y, like_p, work, B, context) at t = 0. In a family's loop over a block's members, remember(work,
    B, j, y) keeps a member's state before its step (y, in the family's coordinates). After that loop,
    watch(like_y, like_p, work, B, t1, levels, context) evaluates every member's signs at its new state at t1 (s,
    the step's end; to_user: a splitting's from_pieces to the scene's coordinates, or None) in a loop of its own
    and says whether any may have crossed (`any_straddles`, in a boolean, which LLVM keeps in a vector's mask: a
    float sum, which it may not reorder, kept the loop from vectorizing); where any did, locate(like_y, like_p,
    work, B, t, h, context) (`fixed_locate`) finds the members that crossed (`crossed`; their signs at the step's
    start made anew from their state there), then takes each, its values at both ends, and locates its events on
    advance(t0, h, y0, p), the family's step in the scene's coordinates (runge_kutta.advance_of,
    splitting.advance_of); the member stops at the first that stops it. steps: NO_STEPS with watch and locate
    (`watched_steps`). Rows are stored whole (a value selected against the row's became a masked store, slow on AMD
    Zen 3) at rows fixed when compiled (else LLVM cannot prove a block's members apart); watched in the step's own
    loop, a top's tilt kept it from vectorizing. context: (events, status, failure_time, j0) from frames."""
    like_g, begin, locate = (0.0,) * E, beginning(signs, first, E), fixed_locate(values, signs, advance, to_user,
                                                                                 first, E)
    G, _, OLD = fixed_rows(first, E)

    @njit(inline="always", **FAST)
    def remember(work, B, j, y):
        stored(work, OLD, B, j, y)

    @njit(inline="always", **FAST)
    def watch(like_y, like_p, work, B, t1, levels, context):
        D = len(like_y)
        hits = False
        for j in range(B):
            p = loaded(work, D, B, j, like_p)
            before = loaded(work, G, B, j, like_g)
            after = signs(t1, user_state(to_user, loaded(work, 0, B, j, like_y), p), p, levels)
            stored(work, G, B, j, after)
            hits |= any_straddles(before, after)
        return hits

    @njit(inline="always", **FAST)
    def steps(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, context):
        watched_steps(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, watch, locate,
                      levels_and_directions(context[0][0], like_g)[0], context)  # read once a save interval
    return begin, remember, steps


def adaptive_watcher(values, signs, advance, first: int, E: int):
    """(begin, levels_of, watch) for an adaptive kernel (ensemble.engine.frames.adaptive) whose event rows start at
    `first`: begin(like_y, like_p, work, B, context) at t = 0; levels_of(context), the events' levels (a tuple),
    read once per block: constants of its loops, so that what a scene's watch makes of a level (the top's cos and
    sin) is made once, not at every step (LLVM cannot move a load from the spec past the loop's stores); watch(
    like_y, like_p, work, B, K, NEW, C0, S, levels, context) after control_step, before the accepted steps move to
    their new states: each event's sign (`signs_chain`) at the trial state, kept in rows from `first` where the
    step was accepted, and where one crossed, the member's signs at the step's start made anew (as fixed_watcher's
    locate makes them), its values at both ends, its events located on advance (adaptive.advance_of, the pair's
    step). E: the events' count."""
    located, like_g, begin = locator(values, advance), (0.0,) * E, beginning(signs, first, E)
    G = first

    @njit(inline="always", **FAST)
    def levels_of(context):
        return levels_and_directions(context[0][0], like_g)[0]

    @njit(inline="always", **FAST)
    def watch(like_y, like_p, work, B, K, NEW, C0, S, levels, context):
        arrays, status, failure_time, j0 = context
        D = len(like_y)
        directions = levels_and_directions(arrays[0], like_g)[1]
        zeros = repeated(0.0, like_g)
        hits = 0
        for j in range(B):
            before = loaded(work, G, B, j, like_g)
            after = signs(work[(C0 + TIME) * B + j], loaded(work, NEW, B, j, like_y), loaded(work, D, B, j, like_p),
                          levels)
            now = accepted(work, C0, B, j)
            for e in range(E):
                work[(G + e) * B + j] = select(now, after[e], before[e])
            hits += now & any_straddles(before, after)
        if hits:
            for j in range(B):
                p, y0 = loaded(work, D, B, j, like_p), loaded(work, 0, B, j, like_y)
                t1, h = work[(C0 + TIME) * B + j], work[(C0 + STEP) * B + j]
                before, after = signs(t1 - h, y0, p, levels), loaded(work, G, B, j, like_g)  # G: the trial's now
                if accepted(work, C0, B, j) and any_crossed(before, after, zeros, directions):
                    when = located(arrays, j0 + j, t1 - h, h, y0, p, values(t1 - h, y0, p),
                                   values(t1, loaded(work, NEW, B, j, like_y), p),
                                   crossed_each(before, after, zeros, directions))
                    if when == when:
                        stop_member(work, NEW, D, B, j, status, failure_time, j0, when)
                        work[(C0 + H) * B + j] = 0.0  # no further steps
    return begin, levels_of, watch


@njit(inline="always", **FAST)
def accepted(work, C0, B, j):
    """Whether member j's trial step was accepted by its control (a boolean)."""
    return (work[(C0 + REJECTED_LAST) * B + j] == 0.0) & (work[(C0 + ERR) * B + j] >= 0.0)


@njit(inline="always", **FAST)
def stop_member(work, row, D, B, j, status, failure_time, j0, when):
    """Member j stops at an event at time `when` (s): status STOPPED, its state rows from `row` NaN, the time in
    failure_time (the launch counts its steps up to it, then clears it: a stop is not a failure)."""
    status[j0 + j] = STOPPED
    failure_time[j0 + j] = when
    for c in range(D):
        work[(row + c) * B + j] = np.nan
