"""The explicit Runge-Kutta family: one member's step, and the CPU kernels' save interval.

A tableau is (stages, b), tuples of floats as `ensemble.engine.kernels` writes them into a kernel's file: stage s
is its Butcher row (c_s, a_s0, .., a_s,S-1), its node then its weights of the stages' slopes (zero from a_ss on);
b holds the S weights of the step. A scene gives rhs(t, *y, *p) -> D slopes. `step` is a member's whole step, its stage
slopes in registers; the CUDA kernels call it for a thread's member (ensemble.engine.gpu), the CPU kernels for
each member of a block (`members_interval`). Every function here is inlined into the kernel, where the tableau is
a constant; the stages are written out (tuples.unrolled), and LLVM folds the zero coefficients away.
"""
from __future__ import annotations

from numba import njit
from numba.cpython.unsafe.tuple import tuple_setitem

from .blocks import FAST
from .tuples import combined, converted, loaded, repeated, stored


@njit(inline="always", **FAST)
def stage(rhs, t, h, y, p, row, slopes):
    """A stage's slopes, row its Butcher row: rhs at t + c_s h and y + sum_r (h a_sr) slopes[r], in y's type."""
    z = combined(y, h, row, slopes, 1)
    return converted(rhs(t + row[0] * h, *z, *p), y)


@njit(inline="always", **FAST)
def step(rhs, t, h, y, p, stages, b, stage_loop):
    """One member's step of size h (s) from time t (s) and state y, parameters p: the new state. stage_loop:
    tuples.unrolled(S), which writes the stages out."""
    slopes = stage_loop(_stage_slopes, repeated(y, b), rhs, (t, h, y, p, stages))
    return combined(y, h, b, slopes)


@njit(inline="always", **FAST)
def _stage_slopes(s, slopes, rhs, context):
    t, h, y, p, stages = context
    return tuple_setitem(slopes, s, stage(rhs, t, h, y, p, stages[s], slopes))


def members_interval(rhs, tableau, stage_loop):
    """interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context) for
    frames.fixed_step: save interval i (its steps_per_save steps of h, s) of a block of B members, each member's
    whole step at a time, its events watched by remember and steps (ensemble.engine.events.NO_STEPS, or
    fixed_watcher's): state in work rows 0 .. D - 1, parameters in D .. D + P - 1 (like_y, like_p: tuples of D
    and P). stage_loop: tuples.unrolled(S)."""
    stages, b = tableau

    @njit(inline="always", **FAST)
    def members_step(like_y, like_p, work, B, h, t, remember):
        D = len(like_y)
        for j in range(B):
            y, p = loaded(work, 0, B, j, like_y), loaded(work, D, B, j, like_p)
            remember(work, B, j, y)
            stored(work, 0, B, j, step(rhs, t, h, y, p, stages, b, stage_loop))

    @njit(inline="always", **FAST)
    def interval(like_y, like_p, work, B, i, h, steps_per_save, remember, steps, context):
        steps(members_step, like_y, like_p, work, B, i, h, steps_per_save, remember, context)
    return interval


def advance_of(rhs, tableau, stage_loop):
    """advance(t0, h, y0, p): one member's step of h (s) from (t0, y0), the method's own path through a step
    (ensemble.engine.events locates crossings on it)."""
    stages, b = tableau

    @njit(inline="always", **FAST)
    def advance(t0, h, y0, p):
        return step(rhs, t0, h, y0, p, stages, b, stage_loop)
    return advance
