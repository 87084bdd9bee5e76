"""The splittings and compositions: one member's step as the scene's pieces applied in the method's sequence, and
the CPU kernels' save interval.

A method's sequence is entries (piece number, fraction of the step). A scene gives, for each piece it names,
piece(tau, *y, *p, *f) -> D values, where f are the values of `<piece>_factors(tau, *p)` if the scene has that
function (computed once per member, entry and save interval, not per step; a piece without one gets no f), and
may give to_pieces(*y, *p) and from_pieces(*y, *p), a change of coordinates around each save interval.

`sequence_step` and `sequence_factors` write a sequence out as a chain of inlined functions, one link an entry,
its piece and fraction constants of the link (a loop over the entries with a branch per piece was left rolled
for a long sequence: the free body's rotations2 ran 3.6 times faster written out). The CPU kernels
(`members_interval`) and the CUDA kernels (ensemble.engine.gpu) call the same chains, each compiled by its device.
"""
from __future__ import annotations

from functools import cache

from numba import njit

from .blocks import FAST
from .tuples import converted, loaded, stored


def _inlined(function):
    return njit(inline="always", **FAST)(function)


@cache
def sequence_step(entries: tuple, compiled=_inlined):
    """step(h, y, p, factors) -> the state after every entry (piece, fraction) in turn, each piece called as
    piece(h fraction, *y, *p, *factors[e]) (factors: sequence_factors's tuple; h in s, y and p tuples). compiled
    compiles each link (default: Numba's njit, inlined; ensemble.engine.gpu passes numba-cuda's device jit)."""
    if not entries:
        def step(h, y, p, factors):
            return y
        return compiled(step)
    previous, (piece, fraction), e = sequence_step(entries[:-1], compiled), entries[-1], len(entries) - 1

    def step(h, y, p, factors):
        return piece(h * fraction, *previous(h, y, p, factors), *p, *factors[e])
    return compiled(step)


@cache
def sequence_factors(entries: tuple, compiled=_inlined):
    """factors(h, p) -> a tuple with, per entry (factors function or None, fraction), the function's values at
    tau = h fraction and the member's parameters p, or () for a piece without one."""
    if not entries:
        def factors(h, p):
            return ()
        return compiled(factors)
    previous, (function, fraction) = sequence_factors(entries[:-1], compiled), entries[-1]
    if function is None:
        def factors(h, p):
            return previous(h, p) + ((),)
    else:
        def factors(h, p):
            return previous(h, p) + (function(h * fraction, *p),)
    return compiled(factors)


def members_interval(step, factors, like_factors, entered=None, left=None):
    """interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context) for
    frames.fixed_step: save interval i (its steps_per_save steps of h, s) of a block of B members, a step of all
    its members at a time, its events watched by remember and steps (ensemble.engine.events.NO_STEPS, or
    fixed_watcher's).
    Work rows: state
    (D), parameters (P), then each entry's factors (shaped like like_factors). step, factors: sequence_step and
    sequence_factors of the method's sequence; entered, left: a scene's to_pieces and from_pieces (both or
    neither), applied to each member before and after the interval's steps."""
    @njit(inline="always", **FAST)
    def members_step(like_y, like_p, work, B, h, t, remember):
        D, P = len(like_y), len(like_p)
        for j in range(B):
            y, p = loaded(work, 0, B, j, like_y), loaded(work, D, B, j, like_p)
            remember(work, B, j, y)
            stored(work, 0, B, j, converted(step(h, y, p, loaded(work, D + P, B, j, like_factors)), y))

    @njit(inline="always", **FAST)
    def factored_steps(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context):
        D, P = len(like_y), len(like_p)
        for j in range(B):
            stored(work, D + P, B, j, factors(h, loaded(work, D, B, j, like_p)))
        steps(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, context)
    if entered is None:
        @njit(inline="always", **FAST)
        def interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context):
            factored_steps(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context)
        return interval

    @njit(inline="always", **FAST)
    def changed(change, like_y, like_p, work, B):
        for j in range(B):
            y, p = loaded(work, 0, B, j, like_y), loaded(work, len(like_y), B, j, like_p)
            stored(work, 0, B, j, converted(change(*y, *p), y))

    @njit(inline="always", **FAST)
    def interval_changed(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context):
        changed(entered, like_y, like_p, work, B)
        factored_steps(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context)
        changed(left, like_y, like_p, work, B)
    return interval_changed


def interval_of(pieces: tuple, factors: tuple, to_pieces, from_pieces, sequence: tuple, like_factors: tuple):
    """members_interval of a scene's splitting functions (kernels.splitting_functions: pieces and their factors
    functions or None by piece number, to_pieces and from_pieces or None) for a sequence of (piece number,
    fraction) entries; like_factors: each entry's factors, a tuple of as many values."""
    step = sequence_step(tuple((pieces[number], fraction) for number, fraction in sequence))
    factor_values = sequence_factors(tuple((factors[number], fraction) for number, fraction in sequence))
    return members_interval(step, factor_values, like_factors, to_pieces, from_pieces)


def advance_of(pieces: tuple, factors: tuple, to_pieces, from_pieces, sequence: tuple):
    """advance(t0, h, y0, p): one member's step of h (s) from y0 in the scene's coordinates (interval_of's
    arguments), the splitting's own path through a step (ensemble.engine.events locates crossings on it)."""
    step = sequence_step(tuple((pieces[number], fraction) for number, fraction in sequence))
    factor_values = sequence_factors(tuple((factors[number], fraction) for number, fraction in sequence))
    if to_pieces is None:
        @njit(inline="always", **FAST)
        def advance(t0, h, y0, p):
            return converted(step(h, y0, p, factor_values(h, p)), y0)
        return advance

    @njit(inline="always", **FAST)
    def advance_changed(t0, h, y0, p):
        z = converted(step(h, converted(to_pieces(*y0, *p), y0), p, factor_values(h, p)), y0)
        return converted(from_pieces(*z, *p), y0)
    return advance_changed
