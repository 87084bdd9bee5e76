"""The embedded adaptive pairs (dopri5): one member's trial step and its error norm, which the CPU and the CUDA
kernels both call, and the CPU's sweep of a block's trial steps.

A pair is (stages, error): the stages' Butcher rows as in ensemble.engine.runge_kutta, (c_s, a_s0, .., a_s,S-1),
and the error weights b - b_hat, so that h sum_s error[s] k_s estimates a step's local error. The pairs are FSAL:
a step's first slopes are the last step's last, taken at the new state, which is the last stage's state.
"""
from __future__ import annotations

import math

from numba import njit
from numba.cpython.unsafe.tuple import tuple_setitem

from .blocks import ATOL, ERR, FAST, RTOL, STEP, TIME
from .tuples import combined, converted, loaded, repeated, stored


@njit(inline="always", **FAST)
def trial_step(rhs, time, step, y, p, first_slopes, stages, stage_loop):
    """A trial step of size `step` (s) from `time` (s) and state y, parameters p, its first stage's slopes given:
    (every stage's slopes, the new state: the last stage's). stage_loop: tuples.unrolled(S)."""
    return stage_loop(_trial_stage, (repeated(converted(first_slopes, y), stages), y), rhs,
                      (time, step, y, p, stages))


@njit(inline="always", **FAST)
def _trial_stage(s, carry, rhs, context):
    slopes, new = carry
    time, step, y, p, stages = context
    if s == 0:  # the first slopes are given
        return carry
    new = combined(y, step, stages[s], slopes, 1)
    return tuple_setitem(slopes, s, converted(rhs(time + stages[s][0] * step, *new, *p), y)), new


@njit(inline="always", **FAST)
def error_norm(step, y, new, slopes, error, rtol, atol):
    """A trial step's error norm: the RMS over the state's values of step sum_s error[s] slopes[s] over
    atol + rtol max(|y|, |new|). Below 1 the step is accepted. (No literal: a float32 kernel stays float32.)"""
    total = _error_squared(step, y, new, slopes, error, rtol, atol, 0)
    for c in range(1, len(y)):
        total += _error_squared(step, y, new, slopes, error, rtol, atol, c)
    return math.sqrt(total / len(y))


@njit(inline="always", **FAST)
def _error_squared(step, y, new, slopes, error, rtol, atol, c):
    """error_norm's term of value c."""
    estimate = error[0] * slopes[0][c]
    for s in range(1, len(error)):
        estimate += error[s] * slopes[s][c]
    q = step * estimate / (atol + rtol * max(abs(y[c]), abs(new[c])))
    return q * q


@njit(inline="always", **FAST)
def trial_sweep(rhs, pair, stage_loop, like_y, like_p, work, B, K, NEW, C0):
    """Every member of a block takes its trial step (STEP, from TIME; a member with none takes one of size 0):
    the last stage's slopes into rows K + D (S - 1) on, the new state into rows NEW on, the error norm into ERR.
    Rows: state from 0, parameters from D, the first slopes from K, the control block from C0 (blocks.H ..)."""
    stages, error = pair
    D, S = len(like_y), len(stages)
    for j in range(B):
        y, p = loaded(work, 0, B, j, like_y), loaded(work, D, B, j, like_p)
        step, time = work[(C0 + STEP) * B + j], work[(C0 + TIME) * B + j]
        slopes, new = trial_step(rhs, time, step, y, p, loaded(work, K, B, j, like_y), stages, stage_loop)
        stored(work, K + D * (S - 1), B, j, slopes[S - 1])
        stored(work, NEW, B, j, new)
        work[(C0 + ERR) * B + j] = error_norm(step, y, new, slopes, error, work[(C0 + RTOL) * B + j],
                                              work[(C0 + ATOL) * B + j])


def advance_of(rhs, pair, stage_loop):
    """advance(t0, h, y0, p): one member's trial step of h (s) from (t0, y0), its new state: the pair's own path
    through a step (ensemble.engine.events locates crossings on it)."""
    stages = pair[0]

    @njit(inline="always", **FAST)
    def advance(t0, h, y0, p):
        return trial_step(rhs, t0, h, y0, p, converted(rhs(t0, *y0, *p), y0), stages, stage_loop)[1]
    return advance
